"""``python -m physmorph.settings --schema | --defaults``: the maintenance command of
physmorph.settings.schema."""

from physmorph.settings.schema import main

main()
