"""The projector: the pile rebuilt from the ledger as of a valid time V and a known time K.

A fold, ``apply(state, event)``, that updates its state in place and does no I/O; I/O
lives at the edges (:mod:`projector.query` reads the store, :mod:`projector.cli` prints).

Kernels (numpy arrays in and out, no state):

- :mod:`projector.grid`: one grid geometry, named float layers, index <-> position
- :mod:`projector.kinematics`: the reclaimer's kinematics, shared by the projector, the
  localizer, the planner and the dashboard (docs/domain.md §3)
- :mod:`projector.georef`: scanner poses at scan times (slerp), scans -> site points
- :mod:`projector.profile`: mixed pixels and outliers out of each scan profile, line fits
- :mod:`projector.ground`: scanner heights referenced to the ground each scan sees
- :mod:`projector.heightmap`: per-cell Kalman height fusion with Mahalanobis gating
- :mod:`projector.elevation`: hole filling, heights at cell centres, volume
- :mod:`projector.surface_fit`: local least-squares planes and quadratics
- :mod:`projector.layers`, :mod:`projector.deposits`: the monotone layer stack, its
  deposits and what a cut removes from them
- :mod:`projector.slump`: the angle of repose, repose cones and face relaxation
- :mod:`projector.envelope`: the reclaimer's cutting-envelope floor
- :mod:`projector.voxels`: exact voxel integration of deposit bands (QVO)
- :mod:`projector.grades`: assays joined to deposition times as known at K

The fold, split by concern:

- :mod:`projector.config`: :class:`~projector.config.FoldConfig`
- :mod:`projector.state`: :class:`~projector.state.ProjectorState` and its records
- :mod:`projector.fold`: ``apply``, ``flush``, the event handlers, ``FOLD_VERSION``
- :mod:`projector.scans`: scans into the height map in batches
- :mod:`projector.follow`: the layer stack follows the height map
- :mod:`projector.attribution`, :mod:`projector.crossings`: whose pass a rise is, and when
  it was laid
- :mod:`projector.completion`, :mod:`projector.repose`: what the scans did not see
- :mod:`projector.cuts`: the fold's steps of a reclaim cut

At the edges: :mod:`projector.query` (``project``, the snapshot store, the grade join,
``PileState``) and :mod:`projector.cli` (``stockpile project``).
"""
