"""The grade join: which assays count as known at K (projector.grades) and how material
takes its grade and density from them (projector.query.GradeJoin), with exact figures."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from projector.grades import (AssayRecord, coerce_time_ns, effective_assays, grade_at,
                              grade_classes)
from projector.query import GradeJoin, analytes_of
from schemas import pb


def assay(assay_id, start, end, recorded, *, lot="L1", status="FINAL", supersedes="",
          density=0.0, **analytes):
    return AssayRecord(assay_id, lot, start, end, analytes or {"Fe": 60.0}, density, status,
                       supersedes, recorded)


def ids(assays):
    return [a.assay_id for a in assays]


# -- times and records --------------------------------------------------------------------


def test_coerce_time_ns():
    assert coerce_time_ns(5) == 5 and type(coerce_time_ns(np.int64(7))) is int
    assert coerce_time_ns(SimpleNamespace(seconds=3, nanos=4)) == 3_000_000_004
    with pytest.raises(TypeError, match="^a time must be a Timestamp or integer ns, got a bool$"):
        coerce_time_ns(True)
    with pytest.raises(TypeError, match="got str"):
        coerce_time_ns("5")
    with pytest.raises(TypeError, match="got SimpleNamespace"):
        coerce_time_ns(SimpleNamespace(seconds=3))


def test_an_assay_record_checks_its_fields():
    a = AssayRecord("A", "L", np.int64(1), 1, {"Fe": 61, 7: 1}, 0, "PROVISIONAL", "", 9)
    assert a.analytes == {"Fe": 61.0, "7": 1.0} and type(a.analytes["Fe"]) is float
    assert not a.is_final and assay("B", 0, 1, 2).is_final
    for name, kwargs in [("window_start_ns", dict(start=1.0)), ("window_end_ns", dict(end=True)),
                         ("recorded_ns", dict(recorded="9"))]:
        args = dict(start=0, end=1, recorded=2)
        args.update(kwargs)
        with pytest.raises(TypeError, match=f"{name} must be an integer"):
            assay("A", args["start"], args["end"], args["recorded"])
    with pytest.raises(ValueError, match="window ends before it starts"):
        assay("A", 2, 1, 3)
    with pytest.raises(ValueError, match="status must be one of"):
        assay("A", 0, 1, 3, status="final")
    for bad in (-0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="bulk density must be >= 0"):
            assay("A", 0, 1, 3, density=bad)


def test_an_assay_record_from_a_message():
    m = pb.Assay(assay_id="A1", lot_id="L1", analytes={"Fe": 62.5}, status=1,
                 bulk_density_t_m3=2.5, supersedes="A0")
    m.window_start.seconds, m.window_end.seconds, m.window_end.nanos = 10, 20, 5
    a = AssayRecord.from_message(m, 99)
    assert a == AssayRecord("A1", "L1", 10 * 10**9, 20 * 10**9 + 5, {"Fe": 62.5}, 2.5,
                            "PROVISIONAL", "A0", 99)
    assert a.analytes == {"Fe": 62.5}
    assert AssayRecord.from_message(pb.Assay(assay_id="A", lot_id="L", status=2), 1).status == "FINAL"
    plain = SimpleNamespace(assay_id="A", lot_id="L", window_start=1, window_end=2,
                            analytes={"SiO2": 3}, status="final")
    b = AssayRecord.from_message(plain, 5)
    assert (b.status, b.bulk_density_t_m3, b.supersedes, b.window_end_ns) == ("FINAL", 0.0, "", 2)
    with pytest.raises(ValueError, match="unknown status 3"):
        AssayRecord.from_message(SimpleNamespace(**(plain.__dict__ | {"status": 3})), 5)
    with pytest.raises(ValueError, match="unknown status 0"):
        AssayRecord.from_message(pb.Assay(assay_id="A", lot_id="L"), 1)


def test_an_assay_records_the_labs_stated_repeatability():
    m = pb.Assay(assay_id="A1", lot_id="L1", analytes={"Fe": 62.5, "SiO2": 4.0}, status=2,
                 repeatability_pp={"FE": 0.2})
    a = AssayRecord.from_message(m, 1)
    assert a.repeatability_pp == {"Fe": 0.2}          # canonical names, as the analytes
    assert AssayRecord.from_message(pb.Assay(assay_id="A", lot_id="L", status=2),
                                    1).repeatability_pp == {}
    for bad in (0.0, -0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="stated repeatability must be finite"):
            AssayRecord("A", "L", 0, 1, {"Fe": 60}, 0, "FINAL", "", 2, {"Fe": bad})


# -- which assays count at K ----------------------------------------------------------------


def test_only_assays_recorded_by_k_count_and_the_last_copy_wins():
    a1 = assay("A1", 0, 10, 100, Fe=1.0)
    a1_again = assay("A1", 0, 10, 200, Fe=2.0)
    a1_same_time = assay("A1", 0, 10, 200, Fe=3.0)
    a2 = assay("A2", 20, 30, 150)
    assert ids(effective_assays([a1, a2, a1_again], 99)) == []
    assert effective_assays([a1, a2, a1_again], 100) == [a1]
    assert effective_assays([a1_again, a1, a2], 199) == [a1, a2]
    assert effective_assays([a1, a2, a1_again], 200) == [a2, a1_again]
    assert effective_assays([a1_again, a1], 500) == [a1_again]          # an older copy after
    assert effective_assays([a1_again, a1_same_time], 500)[0].analytes == {"Fe": 3.0}
    assert effective_assays([a1], np.int64(100)) == [a1]
    with pytest.raises(TypeError, match="known_ns must be an integer"):
        effective_assays([a1], True)
    with pytest.raises(TypeError, match="known_ns must be an integer"):
        effective_assays([a1], 100.0)


def test_superseded_assays_are_dropped_once_the_replacement_is_known():
    a = assay("A", 0, 10, 100, status="PROVISIONAL")
    b = assay("B", 0, 10, 200, supersedes="A", status="PROVISIONAL")
    c = assay("C", 0, 10, 300, supersedes="B")
    d = assay("D", 50, 60, 300, supersedes="D")   # naming itself: ignored
    assert ids(effective_assays([a, b, c, d], 150)) == ["A"]
    assert ids(effective_assays([a, b, c, d], 250)) == ["B"]
    assert ids(effective_assays([a, b, c, d], 300)) == ["C", "D"]
    # a FINAL is superseded like any other
    f = assay("F", 0, 10, 100)
    g = assay("G", 20, 30, 200, supersedes="F")
    assert ids(effective_assays([f, g], 200)) == ["G"]


@pytest.mark.parametrize("prov,final,dropped", [
    ((0, 10), (10, 20), False),    # touching ends: consecutive windows
    ((10, 20), (0, 10), False),
    ((0, 10), (5, 15), True),
    ((5, 15), (0, 10), True),
    ((0, 10), (11, 20), False),
    ((10, 10), (0, 20), True),     # an instant inside
    ((10, 10), (10, 20), True),    # an instant at an end counts
    ((0, 10), (10, 10), True),
    ((0, 10), (11, 11), False),
    ((3, 3), (3, 3), True),
    ((0, 20), (5, 6), True),
])
def test_a_provisional_assay_gives_way_to_an_overlapping_final_one(prov, final, dropped):
    p = assay("P", *prov, 100, status="PROVISIONAL")
    f = assay("F", *final, 100)
    other_lot = assay("X", *final, 100, lot="L2")
    assert ids(effective_assays([p, f], 100)) == (["F"] if dropped else ["F", "P"])
    assert ids(effective_assays([p, other_lot], 100)) == ["P", "X"]
    # a superseded FINAL drops nothing
    s = assay("S", 90, 95, 100, supersedes="F")
    assert "P" in ids(effective_assays([p, f, s], 100))


def test_effective_assays_are_ordered_by_recorded_time_then_id():
    out = effective_assays([assay("B", 0, 1, 5), assay("A", 2, 3, 5), assay("C", 4, 5, 4)], 10)
    assert ids(out) == ["C", "A", "B"]


# -- which grade a time takes ----------------------------------------------------------------

PLAN = {"Fe": 58.0, "SiO2": 6.0}
AN = ("Fe", "SiO2", "P")


def test_grade_classes_of_integer_times():
    a = assay("A", 10, 20, 100, density=2.0, Fe=61.0)
    b = assay("B", 30, 40, 100, Fe=63.0, SiO2=4.0, P=0.1)
    unused = assay("U", 100, 200, 100, Fe=1.0)
    other = assay("O", 0, 100, 100, lot="L2", Fe=2.0)
    times = np.array([5, 10, 20, 21, 30, 40, 41], np.int64)
    c = grade_classes("L1", PLAN, [a, b, unused, other], times, AN)
    assert c.index.tolist() == [0, 2, 2, 0, 3, 3, 0]
    np.testing.assert_array_equal(c.grade, [[58.0, 6.0, math.nan], [math.nan] * 3,
                                            [61.0, 6.0, math.nan], [63.0, 4.0, 0.1]])
    assert c.assayed.tolist() == [False, False, True, True]
    np.testing.assert_array_equal(c.density_t_m3, [math.nan, math.nan, 2.0, math.nan])
    grade, assayed, density = grade_at("L1", PLAN, [a, b], times, AN)
    assert grade.shape == (7, 3) and grade[1].tolist()[:2] == [61.0, 6.0]
    assert assayed.tolist() == [False, True, True, False, True, True, False]
    np.testing.assert_array_equal(density, [math.nan, 2.0, 2.0, math.nan, math.nan, math.nan, math.nan])


def test_grade_classes_carry_each_assays_stated_repeatability():
    """A row per class: NaN for the planned grade and unknown times, and an assay's
    stated sd per analyte (NaN for an analyte it states none for)."""
    a = AssayRecord("A", "L1", 10, 20, {"Fe": 61.0, "SiO2": 5.0}, 0.0, "FINAL", "", 100,
                    {"Fe": 0.2})
    b = assay("B", 30, 40, 100, Fe=63.0)
    c = grade_classes("L1", PLAN, [a, b], np.array([5, 15, 35], np.int64), AN)
    assert c.lab_sd_pp.dtype == np.float64 and c.lab_sd_pp.shape == (4, 3)
    np.testing.assert_array_equal(c.lab_sd_pp, [[math.nan] * 3, [math.nan] * 3,
                                                [0.2, math.nan, math.nan], [math.nan] * 3])
    join = GradeJoin({"L1": PLAN}, [a, b], 1000, 2.0)
    np.testing.assert_array_equal(join.classes("L1", np.array([15], np.int64)).lab_sd_pp,
                                  [[math.nan] * 2, [math.nan] * 2, [0.2, math.nan]])
    none = join.classes("L9", np.array([15, 16], np.int64)).lab_sd_pp   # an undeclared lot
    assert none.dtype == np.float64 and none.shape == (1, len(join.analytes))
    assert np.isnan(none).all()


def test_grade_classes_of_float_times_mark_unknown_times():
    a = assay("A", 10, 20, 100, Fe=61.0)
    c = grade_classes("L1", PLAN, [a], np.array([math.nan, 15.0, 25.0]), ("Fe",))
    assert c.index.tolist() == [1, 2, 0]
    np.testing.assert_array_equal(c.grade, [[58.0], [math.nan], [61.0]])
    # times as a list of ints, no analytes
    c = grade_classes("L1", PLAN, [a], [15, 25], ())
    assert c.index.tolist() == [2, 0] and c.grade.shape == (3, 0)
    with pytest.raises(ValueError, match=r"shape \(N,\)"):
        grade_classes("L1", PLAN, [a], np.zeros((2, 2)), AN)


def test_grade_classes_keep_nanosecond_times_exact():
    # real UTC ns lose their last digits as floats: integer times must stay integers
    t0 = 1_793_491_200_000_000_000
    a = assay("A", t0 - 1_000, t0, 100, Fe=61.0)
    c = grade_classes("L1", PLAN, [a], np.array([t0, t0 + 1, t0 + 100], np.int64), ("Fe",))
    assert c.index.tolist() == [2, 0, 0]
    c = grade_classes("L1", PLAN, [a], np.array([t0 + 1], np.uint64), ("Fe",))
    assert c.index.tolist() == [0]


def test_an_assay_that_applies_to_no_time_does_not_hide_the_next():
    # lowest precedence first: a provisional assay elsewhere, then a final one that applies
    elsewhere = assay("E", 500, 600, 50, status="PROVISIONAL", Fe=1.0)
    here = assay("H", 0, 20, 100, Fe=62.0, density=0.5)
    c = grade_classes("L1", PLAN, [here, elsewhere], np.array([10], np.int64), ("Fe",))
    assert c.index.tolist() == [2] and c.grade[2, 0] == 62.0
    # a density under 1 t/m3 is still a density
    assert c.density_t_m3.tolist()[2] == 0.5


def test_of_overlapping_assays_final_then_later_then_larger_id_wins():
    t = np.array([15], np.int64)

    def winner(*assays):
        c = grade_classes("L1", PLAN, list(assays), t, ("Fe",))
        return c.grade[c.index[0], 0]

    prov_late = assay("Z", 0, 20, 300, status="PROVISIONAL", Fe=1.0)
    final_early = assay("A", 0, 20, 100, Fe=2.0)
    final_late = assay("B", 0, 20, 200, Fe=3.0)
    final_late_big_id = assay("C", 0, 20, 200, Fe=4.0)
    assert winner(prov_late, final_early) == 2.0
    assert winner(final_early, prov_late) == 2.0
    assert winner(final_late, final_early) == 3.0
    assert winner(final_early, final_late) == 3.0
    assert winner(final_late_big_id, final_late) == 4.0
    assert winner(final_late, final_late_big_id) == 4.0
    assert winner(prov_late, assay("Y", 0, 20, 100, status="PROVISIONAL", Fe=5.0)) == 1.0


# -- the join ------------------------------------------------------------------------------


def test_analytes_are_canonical_first_then_sorted():
    lots = {"L1": {"P": 0.1, "Zn": 1.0, "Fe": 60.0}}
    assays = [assay("A", 0, 1, 2, Mn=0.5, SiO2=3.0)]
    assert analytes_of(lots, assays) == ("Fe", "SiO2", "P", "Mn", "Zn")
    assert analytes_of({}, []) == ()
    assert GradeJoin(lots, assays, 10, 2.0).analytes == ("Fe", "SiO2", "P", "Mn", "Zn")
    assert GradeJoin(lots, assays, 10, 2.0, analytes=["Zn", "Fe"]).analytes == ("Zn", "Fe")


def test_the_join_uses_the_assays_known_at_k_and_defaults_density():
    lots = {"L1": {"Fe": 58.0}, "L2": {"Fe": 50.0}}
    a = assay("A", 10, 20, 100, density=3.0, Fe=62.0)
    b = assay("B", 30, 40, 200, Fe=64.0)                 # no density: the default
    other = assay("O", 10, 40, 100, lot="L2", Fe=51.0)
    times = np.array([15, 35, 50], np.int64)
    early = GradeJoin(lots, [a, b, other], 150, 2.0).classes("L1", times)
    assert early.index.tolist() == [2, 0, 0]
    np.testing.assert_array_equal(early.density_t_m3, [2.0, 2.0, 3.0])
    late = GradeJoin(lots, [a, b, other], 200, 2.0)
    assert set(late.by_lot) == {"L1", "L2"} and ids(late.by_lot["L1"]) == ["A", "B"]
    c = late.classes("L1", times)
    assert c.index.tolist() == [2, 3, 0]
    np.testing.assert_array_equal(c.grade, [[58.0], [math.nan], [62.0], [64.0]])
    np.testing.assert_array_equal(c.density_t_m3, [2.0, 2.0, 3.0, 2.0])
    assert c.assayed.tolist() == [False, False, True, True]


def test_a_declared_lot_without_assays_takes_its_planned_grade():
    join = GradeJoin({"L1": {"Fe": 58.0}, "L2": {"Fe": 50.0}}, [assay("A", 0, 99, 1)], 10, 2.0)
    c = join.classes("L2", np.array([5, 6], np.int64))
    assert c.index.tolist() == [0, 0] and c.grade[0, 0] == 50.0
    # one cell of planned material: one class of two holds it all
    tonnes, sums, assayed_t, graded_t = join.material("L2", np.array([5], np.int64), [3.0])
    assert (tonnes, assayed_t, graded_t) == (6.0, 0.0, 6.0) and sums.tolist() == [300.0]
    tonnes, sums, assayed_t, graded_t = join.material("L2", np.array([5, 6], np.int64), [1, 2])
    assert (tonnes, graded_t) == (6.0, 6.0) and sums.tolist() == [300.0]


def test_an_undeclared_lot_has_no_grade():
    join = GradeJoin({"L1": {"Fe": 58.0}}, [assay("A", 0, 99, 1, lot="L9")], 10, 2.5)
    c = join.classes("L9", np.array([1, 2, 3], np.int64))
    assert c.index.tolist() == [0, 0, 0]
    assert c.grade.shape == (1, 1) and math.isnan(c.grade[0, 0])
    assert c.assayed.tolist() == [False] and c.density_t_m3.tolist() == [2.5]
    tonnes, sums, assayed_t, graded_t = join.material("L9", np.array([1, 2], np.int64), [1.0, 3.0])
    assert (tonnes, assayed_t, graded_t) == (10.0, 0.0, 0.0) and sums.tolist() == [0.0]


def test_material_sums_tonnes_grades_and_assayed_tonnes_per_class():
    lots = {"L1": {"Fe": 58.0, "SiO2": 6.0}}
    a = assay("A", 10, 20, 100, density=3.0, Fe=62.0, SiO2=4.0)
    join = GradeJoin(lots, [a], 100, 2.0)
    times = np.array([15.0, 5.0, 16.0, math.nan])
    volumes = [1.0, 2.0, 0.5, 4.0]
    tonnes, sums, assayed_t, graded_t = join.material("L1", times, volumes)
    # assayed: 1.5 m3 x 3 t/m3; planned: 2 m3 x 2; unknown time: 4 m3 x 2, no grade
    assert tonnes == pytest.approx(4.5 + 4.0 + 8.0)
    assert assayed_t == pytest.approx(4.5) and graded_t == pytest.approx(8.5)
    np.testing.assert_allclose(sums, [4.5 * 62.0 + 4.0 * 58.0, 4.5 * 4.0 + 4.0 * 6.0])
    assert join.material("L1", np.array([], np.int64), []) == (0.0, pytest.approx([0.0, 0.0]), 0.0, 0.0)
    empty = join.material("L1", [], np.array([]))
    assert empty[0] == 0.0 and empty[1].shape == (2,) and empty[2:] == (0.0, 0.0)
