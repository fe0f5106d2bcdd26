"""The projector: the pile rebuilt from the ledger as of a valid time V and a known time K.

A pure fold, ``apply(state, event) -> state``, with no I/O inside; I/O lives at the
edges (:mod:`ledger.projector.project` reads the store, the CLI prints).

- :mod:`ledger.projector.grid`: one grid geometry, named float layers, index <-> position
- :mod:`ledger.projector.georef`: scanner poses at scan times (slerp), scans -> site points
- :mod:`ledger.projector.heightmap`: per-cell Kalman height fusion with Mahalanobis gating
- :mod:`ledger.projector.layers`: the monotone layer stack, deposits, cut clamping
- :mod:`ledger.projector.envelope`: the reclaimer's cutting-envelope floor (DOMAIN.md §3)
- :mod:`ledger.projector.voxels`: exact voxel integration of deposit bands (QVO)
- :mod:`ledger.projector.grades`: assays joined to deposition times as known at K
"""
