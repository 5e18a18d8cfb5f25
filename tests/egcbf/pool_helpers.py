"""Cell functions for the process-pool tests, importable by spawned workers (they are found on ``sys.path``)."""

import os
import signal
import time

DIE, SLEEP = 13, 99  # task seeds: kill the worker running it, or run for a minute


def die_or_answer(task):
    """``(task, {"seed": seed, "pid": worker pid}, None)``; a task with seed ``DIE`` kills its worker instead."""
    if task.seed == DIE:
        os.kill(os.getpid(), signal.SIGKILL)
    if task.seed == SLEEP:
        time.sleep(60)
    time.sleep(0.2)  # long enough for the cells of one pool to run side by side
    return task, {"seed": task.seed, "pid": os.getpid()}, None


class DiesWhenUnpickled:
    """Unpickling it ends the process: a worker that dies before its cell starts."""

    def __reduce__(self):
        return os._exit, (3,)
