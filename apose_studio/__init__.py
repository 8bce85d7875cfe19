"""apose_studio: 6D assembly pose estimation by point-cloud registration, with a browser studio."""

import os

# Open3D's OpenMP loops (RANSAC among them) draw and sum across threads, so two runs differ in the last
# bits; on one thread, its seeded RANSAC repeats exactly. Set before Open3D loads (it reads this once);
# a value the user set wins. torch sets its own thread count (segment.py).
os.environ.setdefault("OMP_NUM_THREADS", "1")
# pykdtree's OpenMP threads (geometry/nn.py: ICP's nearest neighbours) wait for work asleep, not spinning: with
# the cores busy with other work, spinning threads took them from each other and from the work (a 2,500-point
# query with both cores busy: 7.3 ms spinning, 0.7 ms asleep; quiet, 0.73 and 0.70 ms: benchmarks/nn_threads.py).
# OpenBLAS (numpy's matrix products and decompositions) on one thread: the estimator's matrices are small, and
# OpenBLAS's own spinning threads fought pykdtree's (a query's p90 on a quiet machine 7.9 ms with them, 0.8 ms
# without), and an answer cannot depend on how many cores the machine has. 160 fixed-protocol frames
# (benchmarks/tune.py, quiet machine): median 100 -> 77 ms (asleep) -> 60 ms (and one OpenBLAS thread), p95
# 143 -> 114 -> 95 ms, every pose the same to the bit. Read when the runtimes load (before numpy: the CLI, the
# studio and `import apose_studio` first); a value the user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _avx2() -> bool:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            return any(line.startswith("flags") and " avx2" in line for line in f)
    except OSError:
        return False


# OpenBLAS (inside numpy's and scipy's wheels) picks its kernels by the CPU it finds; its AVX-512 kernels sum
# in another order than its AVX2 ones, so one frame gave another pose on an AVX-512 machine (a knife-edge test
# passed on one CI machine and failed on the next; the pose moved from right to wrong-and-unconfident). Its
# Haswell (AVX2) kernels run on every x86-64 CPU since 2013: the same answers on all of them. Takes effect
# only when apose_studio loads before numpy (the CLI and the studio; scripts/test.sh sets it for the tests).
if _avx2():
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
# OpenCV's decoders refuse images over this many pixels (its default is 2^30, 3 GB for a colour image):
# a second line behind safeio's header check (8192 x 8192). Read when cv2 loads.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(8192 * 8192))

__version__ = "0.1.0"
