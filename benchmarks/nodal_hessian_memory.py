"""Peak memory and CPU time of one membrane-incision level of experiments/locking_free.py.

Runs ``opening(kind, cells_per_cut, nu)`` (the largest surface opening of the pre-stretched
membrane cut, sparse solver) in this process and prints one JSON line with the opening [mm],
CPU and wall seconds and the peak resident memory (``ru_maxrss``). Run each level in a fresh
process (compiled executables of earlier levels stay cached and add up):

    PYTHONPATH=. prlimit --as=9000000000 python benchmarks/nodal_hessian_memory.py fem_neo_hookean_nodal 16 0.49
"""

import json
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "experiments"))
import locking_free as lf  # noqa: E402

kind, n, nu = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
t0, w0 = time.process_time(), time.time()
v = lf.opening(kind, n, nu)
print(json.dumps(dict(kind=kind, cells_per_cut=n, nu=nu, opening_mm=v * 1e3, cpu_s=time.process_time() - t0, wall_s=time.time() - w0,
                      maxrss_gb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6)), flush=True)
