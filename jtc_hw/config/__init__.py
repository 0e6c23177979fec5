"""Configuration: one schema engine for every parameter, frozen dataclasses out, files read.

- :mod:`.schema`: the engine (:class:`~.schema.ParamSpec` rows in a
  :func:`~.schema.param_table`, :func:`~.schema.validate_params`); :mod:`.values`: the checks
  of single values and the wording of their errors ("did you mean").
- :mod:`.controller`: the controller's upstream parameters, one table per level, and the frozen
  :class:`~.controller.ControllerConfig`; :mod:`.limits`: a joint's limits.
- :mod:`.controller_file`: the controller's part of a file in (either layout) and out, no I/O.
- :mod:`.reading`: the only module that reads files: strict YAML, a URDF's limits,
  :func:`~.reading.load_config`.

Hardware kinds declare their ``params`` with the same engine (``jtc_hw.hardware`` re-exports it
for drivers), and so does the robot file's ``daemon:`` section (:mod:`jtc_hw.daemon.settings`).
Nothing here imports the controller, the hardware, the daemon or the API: configuration is read
at the edges and handed inward frozen.
"""
