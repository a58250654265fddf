"""``phjax._misc.check_count``: the one check of every integer count argument (samples, chunks,
steps, orders, batch multiples, detector ``top_k``). The seven hand-written copies it replaced
disagreed: ``noise`` took ``order=True`` as 1, ``top_k=2.0`` was refused while ``n=2.0`` was
taken, ``num_nodes="3"`` compared a string with an integer."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import phjax as pj
from phjax._misc import check_count


@given(st.integers(1, 2**40))
def test_integer_values_of_any_type_are_taken(n):
    for v in (n, np.int64(n), float(n), np.array(n)):
        out = check_count(v, "n")
        assert out == n and type(out) is int


@pytest.mark.parametrize("bad", [0, -3, 2.5, True, False, np.bool_(True), "3", b"3", None,
                                 float("nan"), float("inf"), [2], np.array([1, 2])])
def test_everything_else_names_the_argument(bad):
    with pytest.raises(ValueError, match=r"^steps must be an integer >= 1 \(per run\), got "):
        check_count(bad, "steps", note=" (per run)")


def test_a_minimum_other_than_one():
    assert check_count(0, "k", minimum=0) == 0
    with pytest.raises(ValueError, match="k must be an integer >= 2, got 1"):
        check_count(1, "k", minimum=2)


def test_the_library_arguments_use_it():
    """The arguments that checked by hand before: the same rule and message everywhere."""
    t = np.arange(20) / 30.0
    p, q = np.zeros((20, 3)), np.tile([1.0, 0, 0, 0], (20, 1))
    with pytest.raises(ValueError, match="order must be an integer >= 1, got True"):
        pj.tracking.noise.estimate_measurement_noise(t, p, q, order=True)
    with pytest.raises(ValueError, match="multiple_of must be an integer >= 1, got '2'"):
        pj.pad_recordings([t], [p], [q], [t], multiple_of="2")
    curve = pj.hermite_quintic(np.zeros(3), np.ones(3), np.ones(3), np.ones(3))
    with pytest.raises(ValueError, match="num_nodes must be an integer >= 1, got '3'"):
        curve.bending_energy("3")
    with pytest.raises(ValueError, match="chunk must be an integer >= 1, got 2.5"):
        next(pj.sample_chunks(curve, 4, 2.5))
