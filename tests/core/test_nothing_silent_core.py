"""The numpy API's silent and unclear cases of the hostile-user probe (issue 27, core side):
each is refused with a named error or made right."""

import json

import numpy as np
import pytest

import dolfinx_lopinf as lo
from dolfinx_lopinf.errors import FileFormatError, InputError

T = np.arange(300) * 0.01


def _snaps(t=T, **kw):
    Q = np.vstack([np.cos(t - t[0]), np.sin(2 * (t - t[0])), np.cos(3 * (t - t[0]))])
    return lo.Snapshots(t, Q, **kw)


@pytest.fixture(scope="module")
def model():
    return lo.fit(_snaps(), 3, damping=False, mass="identity")


@pytest.mark.parametrize("bad", ["no", "False", "yes", 0.5, None])
def test_damping_must_be_a_boolean_or_auto(bad):
    with pytest.raises(InputError, match="damping must be True, False or 'auto'"):
        lo.fit(_snaps(), 3, damping=bad)


def test_t_end_must_be_a_whole_number_of_steps(model):
    with pytest.raises(InputError, match="not a whole number"):
        model.predict(t_end=0.10499)
    with pytest.raises(InputError, match="not a whole number"):
        model.predict(t_end=0.004)
    assert model.predict(t_end=0.1).Qh.shape[1] == 11


def test_complex_initial_states_are_refused(model):
    with pytest.raises(InputError, match="complex"):
        model.predict(10, q0=1j * np.ones(3))


def _tampered(tmp_path, model, **changes):
    path = model.save(tmp_path / "m.npz")
    data = dict(np.load(path))
    meta = json.loads(str(data["meta"]))
    for key, value in changes.items():
        if key == "basis_rows":
            data[key] = value
        elif value is None:
            meta.pop(key)
        else:
            meta[key] = value
    data["meta"] = np.array(json.dumps(meta))
    out = tmp_path / "bad.npz"
    np.savez(out, **data)
    return out


@pytest.mark.parametrize("changes, match", [
    ({"fit_scheme": "euler"}, "fit_scheme: unknown scheme 'euler'"),
    ({"fit_dt": None}, r"missing: \['fit_dt'\]"),
    ({"fit_dt": -1.0}, "fit_dt must be a positive number"),
    ({"basis_rows": np.full((3, 3), np.nan)}, "NaN or inf"),
])
def test_crafted_model_files_are_named(tmp_path, model, changes, match):
    with pytest.raises(FileFormatError, match=match):
        lo.ReducedModel.load(_tampered(tmp_path, model, **changes))
    assert lo.ReducedModel.load(model.save(tmp_path / "ok.npz")).r == 3


def test_clear_messages_for_the_usual_slips():
    a = _snaps()
    b = _snaps(T * (1 + 1e-7))
    with pytest.raises(InputError, match=r"dt = 0\.01 .*relative difference 1e-07"):
        lo.fit([a, b], 3)
    with pytest.raises(InputError, match=r"snapshots\[1\] and snapshots\[0\] differ in their outputs Y \(2 vs 1 rows\)"):
        lo.fit([_snaps(Y=np.ones((1, 300))), _snaps(Y=np.ones((2, 300)))], 3)
    with pytest.raises(InputError, match="rank 0 only"):
        lo.fit(None, 3)

    class Recorder:  # what lo.SnapshotRecorder looks like to fit
        def snapshots(self):
            return a

        def record(self):
            pass

    with pytest.raises(InputError, match=r"lo\.fit\(rec\.snapshots\(\), r\)"):
        lo.fit(Recorder(), 3)
    short = lo.Snapshots(a.times[:12], a.Q[:, :12])
    with pytest.raises(InputError, match=r"record longer, or pass mass= and damping= \(") as info:
        lo.fit(short, 2, scheme="newmark")  # the scheme was named: not asked for again
    assert "scheme=" not in str(info.value)
    with pytest.raises(InputError) as info:
        lo.pod(np.ones((400, 300)), 250)
    assert len(str(info.value)) < 300  # not hundreds of singular values


def test_time_grids_with_rounding_are_one_rule():
    """float32 times and times offset by 1e6 s: accepted by Snapshots, fit and window alike."""
    for t in (T.astype(np.float32), 1e6 + T):
        s = _snaps(np.asarray(t))
        m = lo.fit(s, 3, damping=False, mass="identity")
        assert abs(m.dt - 0.01) < 1e-6
        assert s.window(float(t[10]), float(t[100])).Q.shape[1] == 91


def test_warnings_from_inside_a_fit_point_at_the_callers_line():
    """The package's warnings name the user's line (errors.warn: the first frame outside the
    package), however deep in a fit they arise - bad-input.md's promise. A stopped solver's
    SolverWarning, and lo.fit's raised-ridge warning (recorded in its final fit and replayed),
    were attributed to lines of inference.py, _blas.py or fit.py."""
    import warnings
    from pathlib import Path

    from dolfinx_lopinf.core import lsq

    from dolfinx_lopinf.core.synthetic import mechanical_data

    Qh, dQh, ddQh, U = mechanical_data("forced", 6, 2000, 0)  # both floors active
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        lo.core.infer_mechanical(Qh, dQh, ddQh, U, solver=lsq.PSDBlocks(method="admm", max_iter=2))
    solver = [w for w in seen if issubclass(w.category, lo.errors.SolverWarning)]
    assert solver and all(w.filename == __file__ for w in solver), [(w.filename, w.lineno) for w in seen]
    d = np.load(Path(__file__).with_name("data") / "comet_gen_alpha_at_t_pod16.npz")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        lo.fit(lo.Snapshots(d["train_times"], d["train_Q"], U=d["train_U"]), 12)
    assert any("ridge" in str(w.message) for w in seen), [str(w.message)[:80] for w in seen]
    assert all(w.filename == __file__ for w in seen), [(w.filename, w.lineno) for w in seen]


@pytest.mark.parametrize("r, match", [(2.5, "must be an integer, got 2.5"),
                                      ("4", "must be an integer, got '4'"),
                                      (True, "must be an integer, got the boolean"),
                                      (0, "must be >= 1, got 0")])
def test_lo_fit_names_a_bad_reduced_dimension(r, match):
    """r = 2.5 and "4" were raw TypeErrors from inside the POD, r = True fitted r = 1, and r = 0
    blamed the data ("the target is identically zero")."""
    with pytest.raises(InputError, match=r"r \(the reduced dimension\) " + match):
        lo.fit(_snaps(), r, damping=False)
