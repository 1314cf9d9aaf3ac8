"""`python -m falsify`: the command line."""

import sys

from falsify.cli import main

if __name__ == "__main__":
    sys.exit(main())
