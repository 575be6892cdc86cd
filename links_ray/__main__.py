"""`python -m links_ray`: the `links` command."""

import sys

from links_ray.cli.main import main

sys.exit(main())
