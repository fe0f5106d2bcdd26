"""The yard simulator: a ground-truth stockyard that speaks the real hardware protocols.

It keeps its own machine kinematics and pile geometry on purpose, independent of the
projector's, the planner's and the localizer's: it is the ground truth every accuracy
figure of the product is measured against, and a seed reproduces a run byte for byte.

- :mod:`sim.kinematics`: bucket-wheel reclaimer kinematics and the cutting envelope
- :mod:`sim.grid`, :mod:`sim.parcels`, :mod:`sim.world`: the pile on a fine deposition grid
  (parcels per deposit; stacking, reclaiming, slumping, exact mass accounting), with
  :mod:`sim.deposition`, :mod:`sim.stacking`, :mod:`sim.reclaiming`, :mod:`sim.relaxation`
  and :mod:`sim.truth`
- :mod:`sim.encoders`, :mod:`sim.gnss`, :mod:`sim.scanner` (:mod:`sim.raycast`): the
  sensors with their errors
- :mod:`sim.grades`: belt grades and the laboratory
- :mod:`sim.scenario`: the scenarios
- :mod:`sim.runner`: a run in site time (:mod:`sim.timetable`, :mod:`sim.motion`,
  :mod:`sim.messages`, :mod:`sim.records`), :mod:`sim.publish` where its events go
- :mod:`sim.pty`: pseudo-terminals the emulated serial devices write to
- :mod:`sim.drive`: planned cuts on the true pile, checked in the simulator's geometry
- :mod:`sim.cli`: ``stockpile sim``
"""
