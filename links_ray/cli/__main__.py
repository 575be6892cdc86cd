"""`python -m links_ray.cli`: the `links` command."""

import sys

from links_ray.cli.main import main

sys.exit(main())
