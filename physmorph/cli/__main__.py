"""python -m physmorph.cli: the `physmorph` command (physmorph.cli.main)."""

from physmorph.cli.main import main

raise SystemExit(main())
