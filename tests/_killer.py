"""Run organlab's CLI and SIGKILL itself at the N-th call of a named function (kill -9 tests).

    python tests/_killer.py MODULE:ATTR[.ATTR] N organlab-arguments...

The function is wrapped where it is looked up (``organlab.surface:write_stl``,
``organlab.engine:Engine._run_carving``, ``os:rename``); at its N-th call the process kills itself
with SIGKILL (no cleanup, no atexit, no finally: what ``kill -9`` does), before the call runs.
"""

import importlib
import os
import signal
import sys


def main():
    target, n, args = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
    module, _, path = target.partition(":")
    owner = importlib.import_module(module)
    *parents, name = path.split(".")
    for p in parents:
        owner = getattr(owner, p)
    real = getattr(owner, name)
    calls = [0]

    def wrapper(*a, **k):
        calls[0] += 1
        if calls[0] == n:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(*a, **k)

    setattr(owner, name, wrapper)
    from organlab.cli import main as cli

    sys.exit(cli(args))


if __name__ == "__main__":
    main()
