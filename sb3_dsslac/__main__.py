"""``python -m sb3_dsslac``: see ``sb3_dsslac.app.cli``."""

import sys

from sb3_dsslac.app.cli import main

if __name__ == "__main__":
    sys.exit(main())
