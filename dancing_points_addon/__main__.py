"""``python -m dancing_points_addon``: see :mod:`dancing_points_addon.cli`."""
import os
import sys

from .argtypes import SINGLE_THREAD_ENV  # (imports no numpy)

if __name__ == "__main__" and sys.argv[1:2] == ["benchmark"]:
    # SPEC §6 latency is one thread: numpy's BLAS too (read when numpy loads)
    for _k in SINGLE_THREAD_ENV:
        os.environ.setdefault(_k, "1")

from .cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
