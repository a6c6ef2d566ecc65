"""The settings' declarations, one module per section: each field with its default, bounds and
meaning (physmorph.settings_base). A foundation: the core (solver, renderer, plasticity, morph loop)
and the workflow's settings (physmorph.config) read them from here."""
