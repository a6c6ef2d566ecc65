"""All of configuration, each setting declared once: how a config class is declared (``base``) and
refuses (``errors``); the library's sections (``mpm``, ``render``, ``plasticity``, ``surface``,
``morph``, ``export``, ``solver_memory``, ``retired``); the workflow's own sections
(``sections``), the study points (``study_points``), the merging of YAML profiles and building
of a section (``build``), the typed ``Settings`` of a workflow run (``workflow``), what rule params
carry (``params``), the memory model (``memory_model``), the sections' one-line texts (``docs``) and
the generated schema and first-defaults record (``schema``; ``python -m physmorph.settings
--schema | --defaults`` writes them).

May import physmorph.base only.
"""
