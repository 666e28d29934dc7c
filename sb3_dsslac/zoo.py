"""``python -m sb3_dsslac.zoo train|enjoy [rl-zoo3 flags]``: rl-zoo3's scripts with DS-SLAC registered (``app.zoo``)."""

import sys

from sb3_dsslac.app.zoo import main

if __name__ == "__main__":
    sys.exit(main())
