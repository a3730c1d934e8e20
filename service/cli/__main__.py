"""`python -m greyfit.service.cli`: the `greyfit` command."""
from greyfit.service.cli.commands import main

raise SystemExit(main())
