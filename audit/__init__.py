"""Audit and reconciliation reports, answered from the ledger alone as known at a time K.

- :mod:`audit.report`: the reports as pure computations (no printing): each reclaim
  cut's grade as estimated when it ended against as known at K (:func:`audit_cuts`),
  the pile's tonnes and grade over valid time (:func:`audit_history`), and the labs'
  lateness, superseded and provisional assays, unknown lots and lots without assays
  (:func:`audit_assays`)
- :mod:`audit.marks`: the valid times of a history and their count (to refuse a range
  that is too long before listing it)
- :mod:`audit.cli`: ``stockpile audit cuts|history|assays``: options, progress on
  stderr during long folds, text tables or one JSON object

Imports flow ``schemas <- ledger | devices <- projector <- audit``: nothing here
imports :mod:`services` or :mod:`planner`.
"""
