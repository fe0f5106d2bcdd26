"""The projector: the pile rebuilt from the ledger as of a valid time V and a known time K.

A pure fold, ``apply(state, event) -> state``, with no I/O inside; I/O lives at the
edges (:mod:`projector.project` reads the store, the CLI prints).

- :mod:`projector.grid`: one grid geometry, named float layers, index <-> position
- :mod:`projector.georef`: scanner poses at scan times (slerp), scans -> site points
- :mod:`projector.heightmap`: per-cell Kalman height fusion with Mahalanobis gating
- :mod:`projector.layers`: the monotone layer stack, deposits, cut clamping
- :mod:`projector.envelope`: the reclaimer's cutting-envelope floor (DOMAIN.md §3)
- :mod:`projector.voxels`: exact voxel integration of deposit bands (QVO)
- :mod:`projector.grades`: assays joined to deposition times as known at K
"""
