"""The ``stockpile`` command and the jobs that span the whole yard (the top layer).

- :mod:`stockpile.cli`: the entry point; one subcommand per job, each registered by
  the package that does it
- :mod:`stockpile.demo`: ``stockpile demo``: the yard as processes (the default), the
  simulator imported in-process (``--in-process``), or the generated sample (``--sample``)
- :mod:`stockpile.yard_demo`: the end-to-end demo: every service and the simulator as
  separate processes, drained and checked (exactly once, the localizer, the projector
  against the simulator's truth)
- :mod:`stockpile.sample`: a generated sample session with bad input planted in it
- :mod:`stockpile.orchestrate`: start, watch and stop the yard's processes around a
  loopback Zenoh router (:class:`~stockpile.orchestrate.Supervisor`)
- :mod:`stockpile.service_cli`: ``stockpile service NAME``: the registry of services
- :mod:`stockpile.run_config`: ``stockpile run --config yard.toml``: a real site's
  services, started and restarted from its config
"""
