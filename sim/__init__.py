"""The yard simulator: a ground-truth stockyard that speaks the real hardware protocols.

It is the truth every accuracy figure is measured against, so it keeps its own models on
purpose (its own kinematics, deposition and cuts), never the projector's code.

The world:

- :mod:`sim.scenario`: scenarios as data (``demo``, ``full-scale``, ``bench-scale``, ``load``;
  ``cohesive``, ``delayed``, ``standing``)
- :mod:`sim.material`: what a cut's faces do after the cut (the scenario's material)
- :mod:`sim.grid`: the deposition grid and stacking patterns
- :mod:`sim.world`: the pile (stacking, cuts, settling, mass and grade accounts), on
  :mod:`sim.parcels` (per-column parcel stacks)
- :mod:`sim.deposition`, :mod:`sim.stacking`, :mod:`sim.reclaiming`,
  :mod:`sim.relaxation`: where released material rests, how a pass is released, what a
  cut takes, how faces fail
- :mod:`sim.kinematics`: the simulator's own reclaimer kinematics and cutting envelope
- :mod:`sim.grades`: belt grades and the laboratory
- :mod:`sim.truth`, :mod:`sim.records`: truth records, ``truth.json`` / ``truth.npz``

The hardware, emulated:

- :mod:`sim.encoders`, :mod:`sim.gnss`, :mod:`sim.scanner` (+ :mod:`sim.raycast`): the
  sensors with their errors
- :mod:`sim.pty`: pseudo-terminals the emulated serial devices write to

The run:

- :mod:`sim.runner`: ``Simulation``, the event-driven run in site time (the reclaim's
  handlers in :mod:`sim.reclaim_run`), on
  :mod:`sim.timetable`, :mod:`sim.motion`, :mod:`sim.messages` and :mod:`sim.rng`
- :mod:`sim.publish`: producers and sinks (JSON lines, Zenoh)
- :mod:`sim.drive`: planned cuts driven into the true pile, checked in its own geometry
- :mod:`sim.cli`: ``stockpile sim``
"""
