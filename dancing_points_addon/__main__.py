"""``python -m dancing_points_addon``: see :mod:`dancing_points_addon.cli`."""
import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
