"""Preloaded by the forkserver of kinreg's local worker pool (see :mod:`kinreg.run.executor`): sets
one BLAS/OpenMP thread in the server, so that every worker forked from it starts with it.

Importing this module changes ``os.environ``; nothing but the forkserver imports it.
"""

from kinreg.run.executor import limit_worker_threads

limit_worker_threads()
