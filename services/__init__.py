"""The yard's services: one Zenoh process each, all of the same shape.

Every service module has ``add_arguments(parser)``, ``config_from_args(args) -> Config`` and
``main(config, *, stopper=None) -> int``; ``stockpile service NAME`` runs one
(:mod:`stockpile.service_cli`).

The shared runtime (what a service imports, through :mod:`services.service`):

- :mod:`services.service`: :class:`~services.service.ServiceRuntime` and the facade of the
  names below
- :mod:`services.zenoh_config`: the shared Zenoh options
- :mod:`services.logfmt`: log lines (logfmt or JSON, via :mod:`common.logs`);
  :mod:`services.status`: the status line
- :mod:`services.stopping`: clean stop on SIGINT/SIGTERM; :mod:`services.inbox`: Zenoh
  callbacks to one consumer
- :mod:`services.publishing`: ledger-bound publishers (epoch, dense sequence, cache)
- :mod:`services.site_time`: "now" in site time (wall clock or the simulator's clock)
- :mod:`services.serial_device`: what the serial-device services share
- :mod:`services.ledger_client`: reads of a running ledger service over Zenoh

The services:

- :mod:`services.scanner` (+ :mod:`services.lms200_scans`): LMS200 telegrams -> ``scan``
- :mod:`services.gnss`: NMEA GGA -> ``location_fix``
- :mod:`services.localizer`: joints and GNSS through a UKF -> poses
  (:mod:`services.localizer_filter`, :mod:`services.localizer_tuning`,
  :mod:`services.localizer_covariance`, :mod:`services.localizer_messages`,
  :mod:`services.localizer_batch`)
- :mod:`services.ledger_service`: the single writer of the ledger, and its read queryables
- :mod:`services.projector_service`: a live projection of one pile
- :mod:`services.dashboard`: the operators' Rerun dashboard (live and offline)
- :mod:`services.loadgen`: a load publisher for tests and benchmarks

The MCAP recorder service lives with its format in :mod:`replay.record`.
"""
