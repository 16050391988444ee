"""`python -m appliance.cli`: the `extensometer` command."""

import sys

from appliance.cli import main

sys.exit(main())
