"""The files the stages write and read back: HDF5 helpers with atomic writes and checksums
(``h5io``), what made a file (``provenance``) and the morph's run files, committed one frame at a
time (``runfile``: ``python -m physmorph.records.runfile RUN.h5`` describes one; ``runfile_cli``,
its command line, tells a run from any other path; ``runkey``, what a run may resume under).

May import physmorph.base and physmorph.settings.
"""
