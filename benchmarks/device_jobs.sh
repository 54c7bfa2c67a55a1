#!/bin/bash
# Whole jobs on a lent GPU machine (benchmarks/README.md, "GPU ... whole jobs").
#
#   bash benchmarks/device_jobs.sh prepare QS_MESH BW_MESH   # here: wheels, data and meshes into .dev/
#   bash benchmarks/device_jobs.sh run                       # there (carry .dev): three jobs, logs in $OUT
#
# prepare: QS_MESH and BW_MESH are meshes made on this machine (a quickstart run's mesh.vtu;
# BrainWeb 5 at 1 mm made by configs/paper_three_compartment_nuts.yaml with the sweep's data
# keys), since fTetWild is not on that machine.  The packages that machine lacks travel as
# one archive of their wheels' files (tests and docs left out: the tree that travels is
# limited to 64 MiB); .dev/ must be git-ignored (.git/info/exclude).
# run: each job under its own time limit (an interrupted run keeps its log), one after another.
set -u
case "${1:-}" in
prepare)
  qs=$2 bw=$3
  rm -rf .dev/wheels .dev/site && mkdir -p .dev/wheels .dev/site .dev/brainweb
  pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d .dev/wheels blackjax arviz arviz-base arviz-stats arviz-plots xarray-einstats h5netcdf \
    nibabel meshio pydantic pydantic-core annotated-types typing-inspection nilearn nitransforms sparsax || exit 1
  for w in .dev/wheels/*.whl; do
    python3 -c "import sys, zipfile
z = zipfile.ZipFile(sys.argv[1])
z.extractall(sys.argv[2], [n for n in z.namelist()
    if '/tests/' not in n and '/_assets/' not in n and not n.startswith('docs/')])" "$w" .dev/site || exit 1
  done
  rm -rf .dev/site/nilearn/datasets/data/fsaverage5 && tar -cJf .dev/site.tar.xz -C .dev/site . || exit 1
  rm -rf .dev/site .dev/wheels
  cp "${BAYESREG_BRAINWEB_DIR:?set it to the folder of the BrainWeb models}/subject05_crisp_v.mnc.gz" .dev/brainweb/
  cp "$qs" .dev/qs_mesh.vtu && cp "$bw" .dev/bw5_1mm_mesh.vtu
  du -sh .dev ;;
run)
  export PYTHONUNBUFFERED=1
  t0=$(date +%s)
  mkdir -p /tmp/site && tar -xJf .dev/site.tar.xz -C /tmp/site || exit 3
  export PYTHONPATH=/tmp/site:$PWD BAYESREG_BRAINWEB_DIR=$PWD/.dev/brainweb
  nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
  python3 -c "import jax; print('jax', jax.__version__, jax.devices())" || exit 4
  job() {  # NAME LIMIT_S ARGS...: one `bayesreg` job, its stage lines and last progress lines
    local name=$1 limit=$2 t=$(date +%s); shift 2
    echo "=== $name (limit $limit s) at +$(( t - t0 )) s"
    timeout -s INT "$limit" python3 -c "import sys; from bayesreg.cli import console
sys.argv[0] = 'bayesreg'; console()" "$@" > "$OUT/$name.log" 2>&1
    echo "=== $name exit $? in $(( $(date +%s) - t )) s"
    grep -E "done \(|verdict|wall time" "$OUT/$name.log" | cut -c1-300
    tr '\r' '\n' < "$OUT/$name.log" | grep -E "chunk/s" | tail -2 | cut -c1-260
  }
  qs=(run configs/quickstart.yaml --set mesh.file=../.dev/qs_mesh.vtu)
  job qs3 190 "${qs[@]}" --set output.dir=/tmp/qs3
  job qs32 110 "${qs[@]}" --set sampler.chains=32 --set sampler.min_draws=50 \
    --set output.reference=none --set output.dir=/tmp/qs32
  job bw1mm 250 run configs/paper_three_compartment_nuts.yaml --set data.source=brainweb \
    --set data.resolution_mm=1.0 --set data.skull_margin_mm=5.0 --set model.interpolation=cubic \
    --set data.subject=5 --set mesh.target_nodes=null --set mesh.file=../.dev/bw5_1mm_mesh.vtu \
    --set output.dir=/tmp/bw1mm
  echo "total $(( $(date +%s) - t0 )) s" ;;
*) echo "usage: $0 prepare QS_MESH BW_MESH | run" >&2; exit 2 ;;
esac
