"""Preloaded by the forkserver of kinreg's local worker pool (see :mod:`kinreg.run.executor`): sets
one BLAS/OpenMP thread in the server, so that every worker forked from it starts with it, and
makes the server end with the process that started it (its workers then end with it).

Importing this module changes ``os.environ`` and this process's parent-death signal; nothing but
the forkserver imports it, first (it preloads the workers' tasks' module after it).
"""

import os

from kinreg.run.executor import die_with_parent, limit_worker_threads

# The server's pid, which every worker forked from it inherits: its parent when it started.
SERVER_PID = os.getpid()

# If the starting process has already ended, the server ends anyway: its "alive" pipe is at EOF
# and no worker holds it yet.
die_with_parent()
limit_worker_threads()
