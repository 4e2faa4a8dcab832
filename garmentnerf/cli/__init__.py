"""The ``garmentnerf`` command line: :mod:`~garmentnerf.cli.main` (the entry point, one-line errors)
and one module per subcommand group.

- :mod:`~garmentnerf.cli.common`: arguments, loaders and checks shared by several subcommands.
- :mod:`~garmentnerf.cli.body_cmd` (``body``), :mod:`~garmentnerf.cli.motion_cmd` (``motion``),
  :mod:`~garmentnerf.cli.maps_cmd` (``maps``), :mod:`~garmentnerf.cli.data_cmd` (``data``),
  :mod:`~garmentnerf.cli.train_cmd` (``train``), :mod:`~garmentnerf.cli.render_cmd` (``render``),
  :mod:`~garmentnerf.cli.eval_cmd` (``eval``, ``report``), :mod:`~garmentnerf.cli.bench_cmd`
  (``bench``), :mod:`~garmentnerf.cli.view_cmd` (``view``) and :mod:`~garmentnerf.cli.view_bench`
  (``view --bench``).
"""
