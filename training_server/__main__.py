"""`python -m training_server`: the same as the `training-server` command."""

from training_server import main

raise SystemExit(main())
