"""``benchmarks/profiling.py``: reading a profile's events and the dumped HLO (no profiler run;
the compiled scopes themselves are checked in ``test_posterior.py``)."""

import pytest

from helpers import load_benchmark


@pytest.fixture(scope="module")
def profiling():
    return load_benchmark("profiling")


def test_event_op_reads_cpu_stats_and_gpu_kernel_annotations(profiling):
    assert profiling.event_op({"hlo_op": "fusion.3", "hlo_module": "jit_chunk", "program_id": 12}) == (
        "jit_chunk", 12, "fusion.3")
    assert profiling.event_op({"hlo_op": "dot.1"}) == (None, None, "dot.1")
    # XLA:GPU's annotation stack (xla/backends/gpu/runtime/annotation.cc), module then thunk;
    # the op name may hold commas
    gpu = ("XlaModule:#prefix=jit(chunk)/vmap,hlo_module=jit_chunk,program_id=7#::"
           "Thunk:#name=while/body/bayesreg_solve/reduce_sum[axes=(0, 1)],hlo_op=loop_fusion.12#")
    assert profiling.event_op({"kernel_annotation": gpu, "correlation_id": 5}) == (
        "jit_chunk", 7, "loop_fusion.12")
    assert profiling.event_op({"kernel_annotation": "Thunk:#hlo_op=copy.4#"}) == (None, None, "copy.4")
    assert profiling.event_op({"correlation_id": 5}) == (None, None, None)
    assert profiling.event_op({"kernel_annotation": "cudaMemcpyAsync"}) == (None, None, None)
    # a kernel run inside a command buffer is known by its own name only
    assert profiling._kernel_name("input_reduce_fusion.2") == "input_reduce_fusion_2"
    assert profiling._kernel_name("triangular-solve.1") == "triangular_solve_1"


_GPU_DUMP = """HloModule jit_chunk, entry_computation_layout={(f64[3]{0})->f64[3]{0}}

%fused_computation (param_0: f64[3]) -> f64[3] {
  %param_0 = f64[3]{0} parameter(0)
  %m = f64[3]{0} multiply(%param_0, %param_0), metadata={op_name="jit(chunk)/bayesreg_similarity/mul"}
  ROOT %a = f64[3]{0} add(%m, %param_0), metadata={op_name="jit(chunk)/bayesreg_solve/add"}
}

ENTRY %main (p: f64[3]) -> f64[3] {
  %p = f64[3]{0} parameter(0)
  %loop_fusion = f64[3]{0} fusion(%p), kind=kLoop, calls=%fused_computation
  ROOT %neg = f64[3]{0} negate(%loop_fusion), metadata={op_name="jit(chunk)/bayesreg_proposal/neg"}
}
"""


def test_hlo_index_files_an_unnamed_fusion_under_its_fused_root(profiling, tmp_path):
    (tmp_path / "module_0007.jit_chunk.sm_9.0_gpu_after_optimizations.txt").write_text(_GPU_DUMP)
    (tmp_path / "module_0007.jit_chunk.before_optimizations.txt").write_text("HloModule other")
    index = profiling.hlo_index(str(tmp_path))
    module, op, control = index[(7, "loop_fusion")]
    assert (module, control) == ("jit_chunk", False)
    assert profiling.part_of(op) == "solve"  # the fused computation's ROOT, not its user
    assert profiling.part_of(index[(7, "neg")][1]) == "proposal"
    assert profiling.part_of(index[(7, "m")][1]) == "similarity"
    assert profiling.step_programs(index) == {7}
    kept = profiling.keep_hlo(str(tmp_path), tmp_path / "kept")
    assert kept == 1 and len(list((tmp_path / "kept").iterdir())) == 1
