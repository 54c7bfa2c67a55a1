"""Two vCPUs: separate cores or SMT siblings?  One worker process pinned to each vCPU, alone and
then both at once, 4 s each; four workloads (in-L1 FMA, L3 and DRAM streaming, pure Python).

Usage: ``python benchmarks/results/cpu-stop41/vcpus.py [ROUNDS]`` (plain NumPy; no JAX).  Stop 41."""
import os, sys, time, multiprocessing as mp
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
import numpy as np

def work(kind, cpu, secs, q):
    os.sched_setaffinity(0, {cpu})
    if kind == "fma":      # L1-resident float64 matmul: FMA-unit bound
        a = np.random.rand(48, 48); b = np.random.rand(48, 48); f = lambda: a @ b
    elif kind == "l3":     # float32 mat-vec streaming an 8 MB matrix (L3)
        a = np.random.rand(1448, 1448).astype(np.float32); x = np.random.rand(1448).astype(np.float32); f = lambda: a @ x
    elif kind == "dram":   # 64 MB float32 matrix (beyond L3)
        a = np.random.rand(4096, 4096).astype(np.float32); x = np.random.rand(4096).astype(np.float32); f = lambda: a @ x
    else:                  # pure-Python integer loop
        def f():
            s = 0
            for i in range(1000):
                s += i
            return s
    for _ in range(20): f()
    n = 0; t0 = time.perf_counter()
    while time.perf_counter() - t0 < secs:
        f(); n += 1
    q.put(n / (time.perf_counter() - t0))

def run(kind, cpus, secs=4.0):
    q = mp.Queue(); ps = [mp.Process(target=work, args=(kind, c, secs, q)) for c in cpus]
    [p.start() for p in ps]; [p.join() for p in ps]
    return [q.get() for _ in cpus]

if __name__ == "__main__":
    for rnd in range(int(sys.argv[1]) if len(sys.argv) > 1 else 2):
        for kind in ("fma", "l3", "dram", "python"):
            a0 = run(kind, [0])[0]; a1 = run(kind, [1])[0]; both = run(kind, [0, 1])
            print(f"round {rnd} {kind:6s}: alone cpu0 {a0:10.0f}/s cpu1 {a1:10.0f}/s | together {both[0]:10.0f} + {both[1]:10.0f} = {sum(both) / ((a0 + a1) / 2):.2f}x one alone", flush=True)
