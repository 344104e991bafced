"""The held-out survey runs and reports every fit it makes (one seed, r = 4)."""

from dolfinx_lopinf.studies import held_out


def test_held_out_survey_certifies_each_kind():
    rows = held_out.run(range(1), r_values=(4,), k_values=(3000,))
    assert [row["kind"] for row in rows] == ["forced", "rigid", "mixed", "short"]
    assert all(row["converged"] and row["gap"] <= 1e-8 and row["ms"] > 0 for row in rows)
    assert {row["path"] for row in rows} <= {"ipm", "ipm+crossover", "symmetric-lsq"}
