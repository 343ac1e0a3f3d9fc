"""Synthetic flight logs in foreign layouts, written from this project's own plant (tests only)."""

import math

import numpy as np

from sim.params import DT


def quat_xyzw(R):
    """Quaternions (n, 4), x y z w, of rotation matrices (n, 3, 3) (Shepperd's method, an independent route)."""
    out = np.empty((len(R), 4))
    for i, m in enumerate(R):
        tr = np.trace(m)
        if tr > 0:
            s = 2.0 * math.sqrt(tr + 1.0)
            w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
        else:
            j = int(np.argmax(np.diag(m)))
            a, b, c = j, (j + 1) % 3, (j + 2) % 3
            s = 2.0 * math.sqrt(1.0 + m[a, a] - m[b, b] - m[c, c])
            q = np.empty(3)
            q[a], q[b], q[c] = 0.25 * s, (m[b, a] + m[a, b]) / s, (m[c, a] + m[a, c]) / s
            w = (m[c, b] - m[b, c]) / s
            x, y, z = q
        out[i] = (x, y, z, w)
    return out


def rot_zyx(e):
    cf, sf, ct, st, cp, sp = (np.cos(e[:, 0]), np.sin(e[:, 0]), np.cos(e[:, 1]), np.sin(e[:, 1]),
                              np.cos(e[:, 2]), np.sin(e[:, 2]))
    Rz = np.zeros((len(e), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = cp, -sp, sp, cp, 1
    Ry = np.zeros_like(Rz)
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 2, 0], Ry[:, 2, 2], Ry[:, 1, 1] = ct, st, -st, ct, 1
    Rx = np.zeros_like(Rz)
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2], Rx[:, 0, 0] = cf, -sf, sf, cf, 1
    return Rz @ Ry @ Rx


def write_nanodrone_parquet(path, states, rotors, t0=0.0, reference=None):
    """Write a flight in the nano-drone benchmark's raw Parquet layout (z-up, FLU, xyzw, eRPM with 6 pole pairs,
    is_flying, position setpoint); ``states`` (n, 12) NED/FRD, ``rotors`` (n, 4) rad/s in the project's order
    (the benchmark's m1..m4 are the same positions)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    n = len(states)
    flip = np.array([1.0, -1.0, -1.0])
    pos, vel, rates = states[:, 0:3] * flip, states[:, 9:12] * flip, states[:, 6:9] * flip
    q = quat_xyzw(flip[:, None] * rot_zyx(states[:, 3:6]) * flip[None, :])
    erpm = rotors * 360.0 / (2.0 * math.pi)
    ref = pos if reference is None else reference * flip
    cols = {"t": t0 + np.arange(n) * DT, "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2],
            "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3],
            "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2], "wx": rates[:, 0], "wy": rates[:, 1], "wz": rates[:, 2],
            **{f"m{i + 1}_erpm": erpm[:, i] for i in range(4)}, "is_flying": np.ones(n, dtype=bool),
            "x_r": ref[:, 0], "y_r": ref[:, 1], "z_r": ref[:, 2], "Vbat": np.full(n, 4.0)}
    pq.write_table(pa.table(cols), path)
