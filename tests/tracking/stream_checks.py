"""Finite-difference checks shared by the tracker stream tests (independent of the tracker's
own velocity formulas)."""

import numpy as np

import phjax as pj


def world_omega(qa, qb, dt):
    """World-frame angular velocity ``2 q' q*`` by a central difference of two unit quaternions
    ``dt`` apart, at their midpoint."""
    qa, qb = np.asarray(qa), np.asarray(qb)
    qm = (qa + qb) / np.linalg.norm(qa + qb, axis=-1, keepdims=True)
    return 2 * np.asarray(pj.quat_mul((qb - qa) / dt, pj.quat_conj(qm)))[..., 1:]
