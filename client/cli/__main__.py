"""`python -m posecast.client.cli ARGS...`: the `posecast` command."""

import sys

from posecast.client.cli import main

sys.exit(main())
