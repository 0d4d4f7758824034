import os

# Every test runs headless.
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("MPLBACKEND", "Agg")

# Under pytest-xdist every core already runs a worker process: the fits' finite differences stay
# on one thread there (recon/threads.py), as more threads than cores only slow each test down
# (a 141 s test took over 300 s with two workers of two threads each beside other load)
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("SHAKERLAB_THREADS", "1")
