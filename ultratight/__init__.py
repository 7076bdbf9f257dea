"""ultratight: a software GPS L1 C/A receiver with ultra-tight (deep) SINS coupling.

Sub-packages, in import order (a package imports only those to its left):

    ins  <-  signals  <-  fusion  <-  receiver

``ultratight.constants`` and ``ultratight.errors`` sit below all of them.

The compiled stages that spread work over numba's threads wait for each other many times a
second; with OpenMP's default busy waiting a second process on the same cores makes them spin
against it (measured: five times slower than one thread at a load average of 7), so unless the
user chose otherwise, waiting threads sleep (``OMP_WAIT_POLICY=PASSIVE``, read when the OpenMP
runtime starts, i.e. before the first parallel region).

The receiver's matrices are small (the tight filter's are at most a few tens of rows), so BLAS
threads gain nothing; OpenBLAS's idle threads spin after every call and took 3-6 % of the CPU
from the engine's own threads (measured on the dlb-rackf benchmark). Unless the user chose
otherwise, BLAS runs on the calling thread (``OPENBLAS_NUM_THREADS=1``, read when numpy loads).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
