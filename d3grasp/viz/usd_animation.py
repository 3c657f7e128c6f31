"""Time-sampled USD animation of a rollout (opens in usdview, Isaac Sim, Blender).

Every recorded world gets its own ``/World/env_<w>`` Xform, laid out on a grid (the simulated worlds
all share one place). Rigid bodies are Xforms with time-sampled ``translate`` and ``orient`` ops and
their visible shapes (boxes, spheres, capsules, cylinders, meshes) as static children; a soft
object is a ``UsdGeom.Mesh`` of its simulation surface triangles with time-sampled ``points``.
The table is a thin cube under the worlds. Units: metres (``metersPerUnit = 1``), Z up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from d3grasp.viz.video import HAND_COLOR, OBJECT_COLOR, PAD_COLOR, SOFT_COLOR, TABLE_COLOR, tile_grid


def _shape_prim(stage, path: str, model, arrays: dict[str, np.ndarray], s: int):
    """Author shape ``s`` at ``path`` (local transform, geometry); None if unsupported.

    ``arrays`` holds the model's shape_type, shape_scale and shape_transform as NumPy arrays.
    """
    import newton
    from pxr import Gf, UsdGeom, Vt

    gt = newton.GeoType
    kind = int(arrays["type"][s])
    scale = arrays["scale"][s]
    if kind == gt.BOX:
        prim = UsdGeom.Cube.Define(stage, path)
        prim.CreateSizeAttr(2.0)
        extra_scale = Gf.Vec3f(*map(float, scale))
    elif kind == gt.SPHERE:
        prim = UsdGeom.Sphere.Define(stage, path)
        prim.CreateRadiusAttr(float(scale[0]))
        extra_scale = None
    elif kind in (gt.CAPSULE, gt.CYLINDER):
        # Newton's capsules and cylinders run along their local Z with half-height scale[1].
        prim = (UsdGeom.Capsule if kind == gt.CAPSULE else UsdGeom.Cylinder).Define(stage, path)
        prim.CreateRadiusAttr(float(scale[0]))
        prim.CreateHeightAttr(2.0 * float(scale[1]))
        prim.CreateAxisAttr("Z")
        extra_scale = None
    elif kind in (gt.MESH, gt.CONVEX_MESH):
        src = model.shape_source[s]
        if src is None:
            return None
        prim = UsdGeom.Mesh.Define(stage, path)
        verts = np.asarray(src.vertices, dtype=np.float64) * np.asarray(scale, dtype=np.float64)
        idx = np.asarray(src.indices, dtype=np.int32).reshape(-1)
        prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(verts.astype(np.float32)))
        prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(idx))
        prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(idx) // 3, 3, dtype=np.int32)))
        prim.CreateSubdivisionSchemeAttr("none")
        extra_scale = None
    else:
        return None
    xf = arrays["transform"][s]
    api = UsdGeom.XformCommonAPI(prim)
    api.SetTranslate(Gf.Vec3d(*map(float, xf[:3])))
    q = xf[3:7]  # x, y, z, w
    UsdGeom.Xformable(prim).AddOrientOp().Set(Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])))
    if extra_scale is not None:
        UsdGeom.Xformable(prim).AddScaleOp().Set(extra_scale)
    return prim


class UsdRecorder:
    """Records body poses and soft-object nodes of chosen worlds as USD time samples."""

    def __init__(self, env, worlds: list[int] | None = None, fps: float = 30.0, spacing: float = 0.5) -> None:
        import newton
        from pxr import Usd, UsdGeom, Vt

        self.env = env
        model, lay = env.model, env.layout
        self.worlds = list(range(env.num_envs)) if worlds is None else [int(w) for w in worlds]
        if not self.worlds or max(self.worlds) >= env.num_envs or min(self.worlds) < 0:
            raise ValueError(f"USD worlds must lie in [0, {env.num_envs}), got {self.worlds}")
        self.fps = float(fps)
        self.every = max(1, round(1.0 / (env.dt * self.fps)))
        self.stage = Usd.Stage.CreateInMemory()
        stage = self.stage
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())

        rows, cols = tile_grid(len(self.worlds))
        self.offsets = {
            w: np.array([(k % cols) * spacing, -(k // cols) * spacing, 0.0])
            for k, w in enumerate(self.worlds)
        }
        table = UsdGeom.Cube.Define(stage, "/World/table")
        table.CreateSizeAttr(1.0)
        centre = np.mean(list(self.offsets.values()), axis=0)
        ext = np.array([cols * spacing, rows * spacing, 0.01])
        UsdGeom.XformCommonAPI(table).SetTranslate(tuple(float(v) for v in (centre[0], centre[1], -0.005)))
        UsdGeom.XformCommonAPI(table).SetScale(tuple(float(v) for v in ext))
        table.CreateDisplayColorAttr([TABLE_COLOR])

        arrays = {
            "type": model.shape_type.numpy(),
            "scale": model.shape_scale.numpy(),
            "transform": model.shape_transform.numpy(),
        }
        shape_body = model.shape_body.numpy()
        shape_flags = model.shape_flags.numpy()
        shape_world = model.shape_world.numpy()
        body_world = model.body_world.numpy()
        visible = (shape_flags & int(newton.ShapeFlags.VISIBLE)) != 0
        pads = set(np.concatenate([lay.pad_shapes[w] for w in self.worlds]).tolist())
        self.body_ops: list[tuple[int, object, object]] = []  # (body, translate op, orient op)
        self.soft: list[tuple[int, int, object]] = []  # (first particle, count, points attr)
        tri = model.tri_indices.numpy() if model.tri_count else np.zeros((0, 3), dtype=np.int32)
        for w in self.worlds:
            wpath = f"/World/env_{w}"
            UsdGeom.XformCommonAPI(UsdGeom.Xform.Define(stage, wpath)).SetTranslate(
                tuple(float(v) for v in self.offsets[w])
            )
            for b in np.nonzero(body_world == w)[0]:
                shapes = np.nonzero((shape_body == b) & (shape_world == w))[0]
                # Visual shapes where a body has them (an object's render mesh), else its colliders.
                shown = shapes[visible[shapes]] if visible[shapes].any() else shapes
                if len(shown) == 0:
                    continue
                bpath = f"{wpath}/body_{b}"
                xf = UsdGeom.Xform.Define(stage, bpath)
                t_op, q_op = xf.AddTranslateOp(), xf.AddOrientOp()
                self.body_ops.append((int(b), t_op, q_op))
                is_obj = int(b) == int(lay.object_body[w])
                for s in shown:
                    prim = _shape_prim(stage, f"{bpath}/shape_{s}", model, arrays, int(s))
                    if prim is not None:
                        color = OBJECT_COLOR if is_obj else PAD_COLOR if int(s) in pads else HAND_COLOR
                        prim.CreateDisplayColorAttr([color])
            n = int(lay.particle_count[w])
            if n:
                p0 = int(lay.particle_start[w])
                faces = tri[(tri[:, 0] >= p0) & (tri[:, 0] < p0 + n)] - p0
                mesh = UsdGeom.Mesh.Define(stage, f"{wpath}/soft_object")
                mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
                mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
                mesh.CreateSubdivisionSchemeAttr("none")
                mesh.CreateDisplayColorAttr([SOFT_COLOR])
                self.soft.append((p0, n, mesh.CreatePointsAttr()))
        self.samples = 0
        self._step = 0

    def capture(self, force: bool = False) -> bool:
        """Write a time sample if this control step is due (every ``self.every``-th call)."""
        from pxr import Gf, Vt

        due = force or self._step % self.every == 0
        self._step += 1
        if not due:
            return False
        env = self.env
        time = float(self.samples)
        bq = env.state_0.body_q.numpy()
        for b, t_op, q_op in self.body_ops:
            p, q = bq[b, :3], bq[b, 3:7]
            t_op.Set(Gf.Vec3d(*map(float, p)), time)
            q_op.Set(Gf.Quatf(float(q[3]), float(q[0]), float(q[1]), float(q[2])), time)
        if self.soft:
            pq = env.state_0.particle_q.numpy()
            for p0, n, attr in self.soft:
                attr.Set(
                    Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pq[p0 : p0 + n], dtype=np.float32)), time
                )
        self.samples += 1
        return True

    def write(self, path: str | Path) -> Path:
        if self.samples == 0:
            raise ValueError("no USD time samples captured")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.stage.SetStartTimeCode(0.0)
        self.stage.SetEndTimeCode(float(self.samples - 1))
        self.stage.Export(str(path))
        return path
