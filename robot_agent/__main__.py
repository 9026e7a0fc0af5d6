"""``python -m robot_agent`` = ``fleet-slam agent`` (what the container runs): the same parser and the same
error handling (a message and exit 2 or 130, never a traceback, for bad input, a missing router
or a signal while waiting for it)."""

import sys

from fleet_slam.cli import main

if __name__ == "__main__":
    sys.exit(main(["agent", *sys.argv[1:]]))
