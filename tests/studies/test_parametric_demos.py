"""The parametric demos end to end in quick mode: the affine terms they read from UFL, the
rows (method, r, mu, split, test_error, stable) of the four methods, the certificate, the
stability at every test parameter, the accuracy targets inside the training range, and the
figures."""

import pytest

pytest.importorskip("dolfinx_lopinf.fem._dolfinx")

KEYS = ("method", "r", "mu", "split", "test_error", "stable")


@pytest.fixture(scope="module")
def membrane(quick_demo):
    return quick_demo("parametric_membrane")


@pytest.fixture(scope="module")
def cantilever(quick_demo):
    return quick_demo("parametric_cantilever")


def _rows(m, **where):
    return [r for r in m["roms"] if all(r.get(k) == v for k, v in where.items())]


def _check_common(m, methods):
    assert m["roms"]
    for row in m["roms"]:
        for key in KEYS:
            assert key in row, key
        assert row["split"] in ("train", "test")
        assert isinstance(row["stable"], bool)
    found = {r["method"] for r in m["roms"]}
    assert set(methods) <= found, found
    # L-OpInf is stable at every parameter, inside and outside the training range
    for row in m["roms"]:
        if row["method"] == "lopinf":
            assert row["stable"], row
            assert row["max_energy_error"] < 1.0


def _inside_target(m, study=None):
    """Inside the range: L-OpInf within 2x of the intrusive ROM or of the projection floor."""
    sel = dict(split="test", inside=True, **({"study": study} if study else {}))
    for row in _rows(m, method="lopinf", **sel):
        same = {r["method"]: r["test_error"] for r in _rows(m, **sel)
                if r["r"] == row["r"] and r["mu"] == row["mu"]}
        ref = min(same.get("intrusive", float("inf")), same["projection"])
        assert row["test_error"] <= 2.0 * ref, (row, same)


def test_membrane_contrast_affine_terms_and_certificate(membrane):
    _, m = membrane
    assert "K(mu) = 1 * K[1] + mu * K[mu]" in m["affine_terms"]["contrast"]
    assert "non-affinely" in m["affine_terms"]["radius"]
    assert max(m["split_check"]["contrast"].values()) < 1e-12
    fits = [f for f in m["fits"] if f["method"] == "lopinf" and f["study"] == "contrast"]
    assert fits
    for f in fits:
        c = f["report"]["certificate"]
        assert c["converged"] and c["duality_gap"] <= 1e-8
        assert "mu >= 0" in c["stable_for"]


def test_membrane_rows_and_targets(membrane):
    _, m = membrane
    _check_common(m, ["lopinf", "intrusive", "projection"])
    _inside_target(m, "contrast")
    _inside_target(m, "radius")
    outside = _rows(m, method="lopinf", split="test", inside=False)
    assert outside and all(r["stable"] for r in outside)


def test_cantilever_terms_rows_and_targets(cantilever):
    _, m = cantilever
    assert "C(mu) = zeta * C[zeta] + E*zeta * C[E*zeta]" in m["affine_terms"]
    assert "K(mu) = E * K[E]" in m["affine_terms"]
    assert m["cone"] == "E >= 0 and zeta >= 0"
    _check_common(m, ["lopinf", "intrusive", "projection"])
    _inside_target(m)
    for f in m["fits"]:
        if f["method"] == "lopinf":
            assert f["report"]["certificate"]["duality_gap"] <= 1e-8


@pytest.mark.parametrize("name, pngs", [
    ("parametric_membrane", ["error_vs_mu_contrast", "error_vs_mu_radius", "fields_contrast",
                             "fields_radius"]),
    ("parametric_cantilever", ["error_vs_E", "error_vs_zeta", "deformed"]),
])
def test_figures_written(quick_demo, name, pngs):
    out, _ = quick_demo(name)
    for png in pngs:
        path = out / f"{png}.png"
        assert path.exists() and path.stat().st_size > 10_000, png
        with open(path, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"
