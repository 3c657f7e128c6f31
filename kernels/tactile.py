"""Tactile pads: net 3-D contact force on each of the 11 pads of every world, in the pad's own frame.

Source data (Newton 1.8, ``SolverVBD`` with ``observables(kinds={"contact_f"})``): ``contact_f`` is a
``wp.spatial_vector`` array of length ``rigid_contact_max + soft_contact_max`` in world frame whose
first three components (``wp.spatial_top``) are the force [N] and last three the torque:

- row ``i < rigid_contact_count[0]``: force on the body of ``rigid_contact_shape0[i]`` exerted by
  ``rigid_contact_shape1[i]``. If a pad is shape0 it receives ``+f``; if it is shape1 it receives
  ``-f`` (Newton's third law). A pad touching a pad gets both.
- row ``rigid_contact_max + j`` (``j < soft_contact_count[0]``): force on the body of
  ``soft_contact_shape[j]`` from the soft particle/edge/face of record ``j``.

Two launches:

1. :func:`accumulate_pad_forces` zeroes and atomically sums the rows of pad shapes into
   ``world_forces[world, pad]`` (world frame).
2. :func:`pad_frame_forces` rotates to the pad frame, ``f_pad = R(q_body * q_pad_in_body)^T f_world``,
   saturates, adds sensor noise and sets the binary contact indicator.

Sensor model (defaults in :class:`TactileConfig`): saturation clips each pad-frame axis to
``[-limit_a, +limit_a]``, with the pad normal on local ``+z``. We assume the Paxini pads' range to be
~25 N normal and ~10 N shear per pad (the paper gives no figure; no datasheet was available offline),
so defaults are ``(10, 10, 25)`` N. Noise is additive zero-mean Gaussian per axis applied after
saturation (the electronics add noise to the saturated reading), seeded per step with
``wp.rand_init(seed, tid)`` from a device-side seed that advances each call. The contact
indicator is ``||f_measured|| > threshold`` (default 0.1 N)
and is returned as float 0/1 so it can be fed to networks and rewards directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

__all__ = [
    "NUM_PADS",
    "TactileConfig",
    "TactileLayout",
    "accumulate_pad_forces",
    "pad_frame_forces",
    "pad_forces_in_pad_frames",
]

NUM_PADS = 11


@dataclass(frozen=True)
class TactileConfig:
    """Sensor model. ``saturation`` per pad-frame axis [N] (<= 0 disables), noise std [N], threshold [N]."""

    saturation: tuple[float, float, float] = (10.0, 10.0, 25.0)
    noise_std: float = 0.0
    contact_threshold: float = 0.1


@wp.kernel
def _accumulate_kernel(
    rigid_count: wp.array(dtype=wp.int32),
    rigid_shape0: wp.array(dtype=wp.int32),
    rigid_shape1: wp.array(dtype=wp.int32),
    soft_count: wp.array(dtype=wp.int32),
    soft_shape: wp.array(dtype=wp.int32),
    contact_f: wp.array(dtype=wp.spatial_vector),
    rigid_contact_max: int,
    shape_pad: wp.array(dtype=wp.int32),
    shape_world: wp.array(dtype=wp.int32),
    shape_object: wp.array(dtype=wp.int32),
    object_only: int,
    out: wp.array2d(dtype=wp.vec3),
):
    tid = wp.tid()
    if tid < rigid_contact_max:
        if tid >= rigid_count[0]:
            return
        f = wp.spatial_top(contact_f[tid])
        s0 = rigid_shape0[tid]
        s1 = rigid_shape1[tid]
        # object_only: a row counts only when the pad's partner is an object shape (a pad pressing
        # the table or another link of the hand is no touch of the object). The table is a static
        # shape (-1 body, shape index >= 0), so it is told apart by the mask, not by the index.
        if s0 >= 0:
            k0 = shape_pad[s0]
            if k0 >= 0 and (object_only == 0 or (s1 >= 0 and shape_object[s1] != 0)):
                wp.atomic_add(out, shape_world[s0], k0, f)
        if s1 >= 0:
            k1 = shape_pad[s1]
            if k1 >= 0 and (object_only == 0 or (s0 >= 0 and shape_object[s0] != 0)):
                wp.atomic_add(out, shape_world[s1], k1, -f)
    else:
        j = tid - rigid_contact_max
        if j >= soft_count[0]:
            return
        s = soft_shape[j]
        # Soft contacts are pad-particle contacts, and every particle belongs to an object.
        if s >= 0:
            k = shape_pad[s]
            if k >= 0:
                wp.atomic_add(out, shape_world[s], k, wp.spatial_top(contact_f[tid]))


@wp.func
def _clip_axis(x: float, lim: float) -> float:
    if lim > 0.0:
        return wp.clamp(x, -lim, lim)
    return x


@wp.kernel
def _pad_frame_kernel(
    world_forces: wp.array2d(dtype=wp.vec3),
    pad_body: wp.array2d(dtype=wp.int32),
    pad_rot_in_body: wp.array2d(dtype=wp.quat),
    body_q: wp.array(dtype=wp.transform),
    saturation: wp.vec3,
    noise_std: float,
    seed: wp.array(dtype=wp.int32),
    threshold: float,
    out_forces: wp.array2d(dtype=wp.vec3),
    out_contact: wp.array2d(dtype=float),
):
    w, k = wp.tid()
    q = pad_rot_in_body[w, k]
    b = pad_body[w, k]
    if b >= 0:
        q = wp.transform_get_rotation(body_q[b]) * q
    f = wp.quat_rotate_inv(q, world_forces[w, k])
    f = wp.vec3(
        _clip_axis(f[0], saturation[0]), _clip_axis(f[1], saturation[1]), _clip_axis(f[2], saturation[2])
    )
    if noise_std > 0.0:
        state = wp.rand_init(seed[0], w * wp.static(NUM_PADS) + k)
        f = f + noise_std * wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    out_forces[w, k] = f
    c = float(0.0)  # noqa: UP018 (Warp: a typed, mutable local)
    if wp.length(f) > threshold:
        c = 1.0
    out_contact[w, k] = c


@wp.kernel
def _advance_seed_kernel(seed: wp.array(dtype=wp.int32)):
    seed[0] = seed[0] + 1


@dataclass
class TactileLayout:
    """Which shapes are pads, in which world, on which body, and each pad's frame in its body.

    Attributes:
        world_count: number of worlds W.
        shape_pad: (shape_count,) int32 pad slot 0..10 for pad shapes, -1 otherwise.
        shape_world: (shape_count,) int32 world of each shape (pads must be in a world >= 0).
        shape_object: (shape_count,) int32 1 for the shapes of the grasped objects, else 0 (what
            ``accumulate_pad_forces(..., object_only=True)`` counts as a pad's partner).
        pad_body: (W, 11) int32 body of each pad (-1: static, identity body rotation).
        pad_rot_in_body: (W, 11) quat, rotation of the pad frame relative to its body.
        noise_seed: (1,) int32 on the device, advanced by one after every :func:`pad_frame_forces`, so
            the noise differs per step also inside a captured graph (a Python int would be frozen).
    """

    world_count: int
    shape_pad: wp.array
    shape_world: wp.array
    pad_body: wp.array
    pad_rot_in_body: wp.array
    device: wp.Device
    noise_seed: wp.array | None = None
    shape_object: wp.array | None = None

    def __post_init__(self) -> None:
        if self.noise_seed is None:
            self.noise_seed = wp.zeros(1, dtype=wp.int32, device=self.device)
        if self.shape_object is None:
            self.shape_object = wp.zeros(self.shape_pad.shape[0], dtype=wp.int32, device=self.device)

    def set_noise_seed(self, seed: int) -> None:
        """Reset the noise stream (host write; do it outside captured graphs)."""
        self.noise_seed.assign(np.array([seed], dtype=np.int32))

    @classmethod
    def from_arrays(
        cls,
        shape_pad: np.ndarray,
        shape_world: np.ndarray,
        shape_body: np.ndarray,
        shape_rot_in_body: np.ndarray,
        world_count: int,
        device: wp.DeviceLike = None,
        shape_is_object: np.ndarray | None = None,
    ) -> TactileLayout:
        """From per-shape arrays: pad slot (-1 = not a pad), world, body, rotation in body (xyzw),
        and optionally which shapes belong to the grasped objects."""
        sp = np.asarray(shape_pad, dtype=np.int64)
        sw = np.asarray(shape_world, dtype=np.int64)
        sb = np.asarray(shape_body, dtype=np.int64)
        sr = np.asarray(shape_rot_in_body, dtype=np.float64).reshape(-1, 4)
        n = len(sp)
        so = np.zeros(n, dtype=bool) if shape_is_object is None else np.asarray(shape_is_object, dtype=bool)
        if not (sw.shape == (n,) and sb.shape == (n,) and sr.shape == (n, 4) and so.shape == (n,)):
            raise ValueError(
                "shape_pad, shape_world, shape_body, shape_rot_in_body, shape_is_object: lengths differ"
            )
        if np.any(sp >= NUM_PADS) or np.any(sp < -1):
            raise ValueError(f"pad slots must be -1 or in [0, {NUM_PADS})")
        is_pad = sp >= 0
        if np.any(is_pad & ((sw < 0) | (sw >= world_count))):
            raise ValueError(f"every pad shape must belong to a world in [0, {world_count})")
        pad_body = np.full((world_count, NUM_PADS), -1, dtype=np.int32)
        pad_rot = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (world_count, NUM_PADS, 1))
        seen = np.zeros((world_count, NUM_PADS), dtype=bool)
        for s in np.nonzero(is_pad)[0]:
            w, k = sw[s], sp[s]
            if seen[w, k]:
                raise ValueError(f"pad slot {k} of world {w} is assigned to more than one shape")
            seen[w, k] = True
            pad_body[w, k] = sb[s]
            pad_rot[w, k] = sr[s] / np.linalg.norm(sr[s])
        dev = wp.get_device(device)
        return cls(
            world_count=world_count,
            shape_pad=wp.array(sp.astype(np.int32), dtype=wp.int32, device=dev),
            shape_world=wp.array(np.maximum(sw, 0).astype(np.int32), dtype=wp.int32, device=dev),
            pad_body=wp.array(pad_body, dtype=wp.int32, device=dev),
            pad_rot_in_body=wp.array(pad_rot.astype(np.float32), dtype=wp.quat, device=dev),
            device=dev,
            shape_object=wp.array(so.astype(np.int32), dtype=wp.int32, device=dev),
        )

    @classmethod
    def from_model(cls, model: object, pad_labels: list[str]) -> TactileLayout:
        """Pads found by ``model.shape_label``: the shape whose label ends with ``pad_labels[k]`` is pad k.

        The pad frame is the shape's own frame (``model.shape_transform`` rotation).
        """
        if len(pad_labels) != NUM_PADS:
            raise ValueError(f"need {NUM_PADS} pad labels, got {len(pad_labels)}")
        labels = list(model.shape_label)
        sp = np.full(len(labels), -1, dtype=np.int64)
        for s, lab in enumerate(labels):
            hits = [k for k, suffix in enumerate(pad_labels) if lab.endswith(suffix)]
            if len(hits) > 1:
                raise ValueError(
                    f"shape label {lab!r} matches several pad labels {[pad_labels[k] for k in hits]}"
                )
            if hits:
                sp[s] = hits[0]
        st = model.shape_transform.numpy()
        return cls.from_arrays(
            sp,
            model.shape_world.numpy(),
            model.shape_body.numpy(),
            st[:, 3:7],
            model.world_count,
            device=model.device,
        )


def accumulate_pad_forces(
    layout: TactileLayout,
    contacts: object,
    contact_f: wp.array,
    out_world: wp.array,
    object_only: bool = False,
) -> None:
    """Sum all contact rows on pad shapes into ``out_world`` ((W,11) vec3, world frame); no host sync.

    ``contacts`` is a ``newton.Contacts`` (or any object with the same array names and
    ``rigid_contact_max``); ``contact_f`` the solver observable of the same layout. ``object_only``
    sums only the contacts with the grasped object (``layout.shape_object``; soft contacts always
    are): the touch of the object, as the success metrics and the closing rule need it.
    """
    rmax = int(contacts.rigid_contact_max)
    n = int(contact_f.shape[0])
    out_world.zero_()
    if n == 0:
        return
    wp.launch(
        _accumulate_kernel,
        dim=n,
        inputs=[
            contacts.rigid_contact_count,
            contacts.rigid_contact_shape0,
            contacts.rigid_contact_shape1,
            contacts.soft_contact_count,
            contacts.soft_contact_shape,
            contact_f,
            rmax,
            layout.shape_pad,
            layout.shape_world,
            layout.shape_object,
            int(bool(object_only)),
        ],
        outputs=[out_world],
        device=layout.device,
    )


def pad_frame_forces(
    layout: TactileLayout,
    world_forces: wp.array,
    body_q: wp.array,
    config: TactileConfig,
    out_forces: wp.array,
    out_contact: wp.array,
) -> None:
    """Pad-frame forces with saturation and noise, and the contact indicator, for all (W,11) pads.

    Noise uses ``wp.rand_init(layout.noise_seed[0], pad id)``; the seed then advances by one on the
    device, so consecutive calls (or graph replays) draw fresh noise.
    """
    wp.launch(
        _pad_frame_kernel,
        dim=(layout.world_count, NUM_PADS),
        inputs=[
            world_forces,
            layout.pad_body,
            layout.pad_rot_in_body,
            body_q,
            wp.vec3(*config.saturation),
            float(config.noise_std),
            layout.noise_seed,
            float(config.contact_threshold),
        ],
        outputs=[out_forces, out_contact],
        device=layout.device,
    )
    wp.launch(_advance_seed_kernel, dim=1, inputs=[layout.noise_seed], device=layout.device)


def pad_forces_in_pad_frames(world_forces: np.ndarray, pad_rotations: np.ndarray) -> np.ndarray:
    """Rotate world-frame pad forces (W,11,3) into pad frames given pad world rotations (W,11,4) xyzw.

    Pure rotation ``f_pad = R(q)^T f_world``: no saturation, no noise.
    """
    f = np.asarray(world_forces, dtype=np.float32)
    q = np.asarray(pad_rotations, dtype=np.float64)
    if f.ndim != 3 or f.shape[1:] != (NUM_PADS, 3):
        raise ValueError(f"world_forces must have shape (W,{NUM_PADS},3), got {f.shape}")
    if q.shape != (f.shape[0], NUM_PADS, 4):
        raise ValueError(f"pad_rotations must have shape ({f.shape[0]},{NUM_PADS},4), got {q.shape}")
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < 1e-9):
        raise ValueError("pad_rotations contains a zero quaternion")
    w = f.shape[0]
    dev = wp.get_device()
    out = wp.zeros((w, NUM_PADS), dtype=wp.vec3, device=dev)
    contact = wp.zeros((w, NUM_PADS), dtype=float, device=dev)
    if w == 0:
        return out.numpy().reshape(0, NUM_PADS, 3)
    wp.launch(
        _pad_frame_kernel,
        dim=(w, NUM_PADS),
        inputs=[
            wp.array(f, dtype=wp.vec3, device=dev),
            wp.full((w, NUM_PADS), -1, dtype=wp.int32, device=dev),
            wp.array((q / norm).astype(np.float32), dtype=wp.quat, device=dev),
            wp.zeros(1, dtype=wp.transform, device=dev),
            wp.vec3(0.0, 0.0, 0.0),
            0.0,
            wp.zeros(1, dtype=wp.int32, device=dev),
            0.0,
        ],
        outputs=[out, contact],
        device=dev,
    )
    return out.numpy()
