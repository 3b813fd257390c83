"""`BodyModel`: the robot's kinematic tree in numpy, for estimating the centre of mass and the feet
from joint angles and the IMU's orientation, as a balance monitor must on hardware.

The tree is a list of rigid bodies in topological order (parent before child). Body b sits at
``pos[b]`` in its parent's frame, turned by ``rot[b]``, then by its hinge joints in order (axis
``axis[j]`` in the body frame, angle q_j, all through the body origin):

    R_b = R_parent(b) · rot_b · Π_j Rot(axis_j, q_j)          Rot(a, θ) = cos θ·I + sin θ·[a]× + (1 − cos θ)·a aᵀ
    p_b = p_parent(b) + R_parent(b) · pos_b
    CoM = Σ_b m_b (p_b + R_b · c_b) / Σ_b m_b                  (c_b: the body's centre of mass, body frame)

The root's orientation R_root is the world orientation (from the IMU; yaw is irrelevant to balance)
and its origin is the frame's origin, so all positions are in a *world-aligned frame centred on the
root body*: horizontal distances (CoM to feet) and heights above the feet are exact, as on hardware.

Geometry comes from the MJCF (`felis.sim.bodymodel.load_body_model`, the one source of geometry) and
masses from the description's ``[links]``. The forward pass is vectorised over the bodies (a
dozen numpy calls, no loop over bodies), reusing scratch buffers: one model per thread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from felis.rotations import quat_matrix


@dataclass(frozen=True)
class BodyModel:
    """A floating-base kinematic tree (see module doc).

    names: body names, topological order, root first; parent: index of each body's parent (−1 root);
    pos / rot: offset (3,) and rotation (3, 3) in the parent frame; com: centre of mass in the body
    frame; mass (kg); joints: (n_bodies, 2) indices into the description's joint order (−1 none);
    axis: (n_joints, 3) unit hinge axes per description joint; feet: body indices of the feet in the
    description's ``sensors.contacts`` order; foot_radius (m): a foot touches the ground that far
    below its centre; imu_rot: the IMU site's orientation in the root body frame; low_body / low_point /
    low_radius: points bounding the collision geometry outside the feet from below (body index, point
    in the body frame, radius; `felis.sim.robot.collision_points`): the robot's lowest point other than
    its feet is min (p_b + R_b · point)_z − radius.
    """

    names: tuple[str, ...]
    parent: np.ndarray
    pos: np.ndarray
    rot: np.ndarray
    com: np.ndarray
    mass: np.ndarray
    joints: np.ndarray
    axis: np.ndarray
    feet: np.ndarray
    foot_radius: float
    imu_rot: np.ndarray
    low_body: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    low_point: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    low_radius: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self):
        n_b, n_j = len(self.names), self.axis.shape[0]
        a = self.axis
        K = np.zeros((n_j, 3, 3))
        K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
        K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = a[:, 2], -a[:, 1], a[:, 0]
        basis = np.stack([np.broadcast_to(np.eye(3), (n_j, 3, 3)), K, a[:, :, None] * a[:, None, :]], axis=1)
        # rotation factors: joints 0..n_j-1, then the identity, then the bodies' constant rotations
        consts = [b for b in range(1, n_b) if not np.allclose(self.rot[b], np.eye(3))]
        buf = np.concatenate([np.zeros((n_j, 3, 3)), np.eye(3)[None], self.rot[consts]])
        const_at = {b: n_j + 1 + i for i, b in enumerate(consts)}
        chains = []
        for b in range(n_b):  # root → b: each body's constant rotation, then its joints, in order
            chain, x = [], b
            while x > 0:
                const = [const_at[x]] if x in const_at else []
                chain = const + [int(j) for j in self.joints[x] if j >= 0] + chain
                x = self.parent[x]
            chains.append(chain)
        depth = max(1, max(len(c) for c in chains))
        factors = np.full((n_b, depth), n_j, dtype=int)  # padded with the identity
        for b, c in enumerate(chains):
            factors[b, :len(c)] = c
        ancestors = np.zeros((n_b, n_b))  # p = ancestors @ offsets, offset_b = R_parent(b) · pos_b
        for b in range(1, n_b):
            x = b
            while x > 0:
                ancestors[b, x] = 1.0
                x = self.parent[x]
        extra = dict(_basis9=np.ascontiguousarray(basis.reshape(n_j, 3, 9)), _rot9=np.zeros((n_j, 1, 9)),
                     _buf=buf, _factors=factors, _ancestors=ancestors, _n_j=n_j,
                     _factor_cols=[np.ascontiguousarray(factors[:, i]) for i in range(depth)],
                     _pos_col=self.pos[:, :, None].copy(), _coef=np.zeros((n_j, 3)),
                     _parent=np.where(self.parent < 0, 0, self.parent), _total=float(self.mass.sum()),
                     _w=self.mass / self.mass.sum(),
                     _wc=(self.mass[:, None] * self.com / self.mass.sum()).ravel(), _imu_rot_t=self.imu_rot.T.copy(),
                     _imu_turned=not np.allclose(self.imu_rot, np.eye(3)),
                     _low_M=low_matrix(self.low_body, self.low_point, n_b), _low_v=np.zeros((n_b, 4)))
        for k, v in extra.items():  # frozen dataclass: precomputed pieces of the forward pass
            object.__setattr__(self, k, v)

    @property
    def total_mass(self) -> float:
        return self._total

    def forward(self, q: np.ndarray, root_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Body origins (n, 3) and rotations (n, 3, 3) in the world-aligned root frame, and the CoM (3,).

        Vectorised over bodies: each body's rotation is the product of the rotation factors on its
        chain from the root (padded with the identity), its origin the sum of its ancestors' offsets.
        """
        coef = self._coef  # (cos q, sin q, 1 − cos q) per joint, in a reused buffer
        np.cos(q, out=coef[:, 0])
        np.sin(q, out=coef[:, 1])
        np.subtract(1.0, coef[:, 0], out=coef[:, 2])
        buf = self._buf
        np.matmul(coef[:, None, :], self._basis9, out=self._rot9)  # Σ_k coef_k · basis_k, as one matmul
        buf[:self._n_j] = self._rot9.reshape(-1, 3, 3)
        cols = self._factor_cols
        P = buf[cols[0]]
        for col in cols[1:]:
            P = P @ buf[col]
        R = root_rot @ P
        offsets = (R[self._parent] @ self._pos_col)[:, :, 0]
        offsets[0] = 0.0
        p = self._ancestors @ offsets
        com = self._w @ p + R.transpose(1, 0, 2).reshape(3, -1) @ self._wc  # Σ w_b (p_b + R_b c_b)
        return p, R, com

    def com_and_feet(self, q: np.ndarray, imu_quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """CoM (3,) and foot centres (k, 3), world-aligned, from joint angles and the IMU quaternion."""
        com, feet, _ = self.com_feet_low(q, imu_quat)
        return com, feet

    def com_feet_low(self, q: np.ndarray, imu_quat: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """`com_and_feet`, and the z of the lowest point other than the feet (NaN without low points)."""
        root_rot = quat_matrix(imu_quat)
        if self._imu_turned:
            root_rot = root_rot @ self._imu_rot_t
        p, R, com = self.forward(np.asarray(q, dtype=float), root_rot)
        low = math.nan
        if self.low_body.size:  # z of each point: R_b[2] · point + p_b,z (`low_matrix`), less its radius
            v = self._low_v
            v[:, :3] = R[:, 2]
            v[:, 3] = p[:, 2]
            z = self._low_M @ v.ravel()
            z -= self.low_radius
            low = float(z.min())
        return com, p[self.feet], low


def low_matrix(body: np.ndarray, point: np.ndarray, n_bodies: int) -> np.ndarray:
    """M (P, 4·n_bodies) with z = M · v the heights of P points fixed in their bodies, where row b of
    v (n_bodies, 4) is (the last row of R_b, z of p_b): z_i = R_b[2] · point_i + p_b,z. One small matrix
    product instead of gathering the bodies' rotations per point."""
    M = np.zeros((len(body), n_bodies, 4))
    M[np.arange(len(body)), body, :3] = point
    M[np.arange(len(body)), body, 3] = 1.0
    return M.reshape(len(body), -1)
