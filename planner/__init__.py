"""The reclaim planner: where to land the bucket wheel, and what the next cuts will deliver.

Pure numerical functions (numpy arrays in and out, no I/O) on the projector's pile model
(:mod:`projector`); the machine's constants and kinematics are the shared
:mod:`projector.kinematics` (:class:`~projector.kinematics.PlannerMachine`: wheel body Rk,
fall angle, bucket width: max cutting height H, advance per cut; inverse kinematics).

- :mod:`planner.landing`: candidate landing points on the surface, normals, wheel
  centres and joints (docs/domain.md §3)
- :mod:`planner.bench`: one cut's slew range and the collision model (wheel body,
  boom, bank, edge), a bench cut by cut on a height map
- :mod:`planner.settle`: the faces a cut leaves slide to the angle of repose
- :mod:`planner.plan`: the landing search and the planned bench on a copy of the
  layer stack, with the projector's removal code
- :mod:`planner.grades`: predicted tonnes, grade and assayed fraction per cut (the
  projector's grade join), grade bounds
- :mod:`planner.cli`: ``stockpile plan reclaim``

``docs/planner.md`` describes the model and its accuracy.
"""
