"""Pictures of rollouts: a tiled GIF, a time-sampled USD animation and a tactile plot.

Checks are on the files as another program reads them back (imageio, pxr): frame count and size,
that frames are not blank, and that the USD holds one time sample per captured frame with the
bodies where the simulation put them (the object on the table, its centre at half its height).
"""

from __future__ import annotations

import numpy as np
import pytest

FRAMES = 10
TILE = (160, 120)  # the smallest tile that gets the phase / pad-force overlay


@pytest.fixture(scope="module")
def rollout(tmp_path_factory):
    import d3grasp
    from d3grasp.envs.baseline import RuleBasedController
    from d3grasp.viz import TactileTrace, UsdRecorder, VideoRecorder

    env = d3grasp.make_env(num_envs=2, eval_mode=True, objects={"ids": ("box_00", "sponge_cube_s")})
    ctl = RuleBasedController(env)
    # fps = control rate: one frame per control step.
    video = VideoRecorder(env, worlds=[0, 1], tile=TILE, fps=1.0 / env.dt, shadows=False)
    usd = UsdRecorder(env, worlds=[0, 1], fps=1.0 / env.dt)
    trace = TactileTrace(env, world=0)
    start = {
        "object_pos": env.state_0.body_q.numpy()[int(env.layout.object_body[0]), :3].copy(),
        "particles": env.state_0.particle_q.numpy()[
            env.layout.particle_start[1] : env.layout.particle_start[1] + env.layout.particle_count[1]
        ].copy(),
    }
    video.capture()
    usd.capture()
    obs = env.get_observations()
    for _ in range(FRAMES - 1):
        obs, _, _, extras = env.step(ctl.act(obs))
        video.capture()
        usd.capture()
        trace.record(extras.get("episodes"))
    out = tmp_path_factory.mktemp("pictures")
    paths = {
        "gif": video.write(out / "rollout.gif"),
        "usd": usd.write(out / "rollout.usda"),
        "png": trace.plot(out / "tactile.png"),
    }
    yield env, paths, start
    env.close()


def test_gif_has_ten_frames_of_the_tiled_size_and_is_not_blank(rollout):
    import imageio.v3 as iio

    _, paths, _ = rollout
    frames = iio.imread(paths["gif"], index=None)
    assert frames.shape[0] == FRAMES
    # Two worlds tile side by side: one row of two tiles.
    assert frames.shape[1:3] == (TILE[1], 2 * TILE[0])
    for f in frames:
        rgb = f[..., :3].astype(np.float64)
        assert rgb.var() > 100.0  # a uniform image has zero variance; table, hand and sky differ
    # The two tiles show different objects: they are not copies of each other.
    assert np.abs(frames[0][:, : TILE[0], :3].astype(int) - frames[0][:, TILE[0] :, :3]).mean() > 1.0


def test_usd_animation_reopens_with_the_expected_time_samples(rollout):
    from pxr import Usd, UsdGeom

    env, paths, start = rollout
    stage = Usd.Stage.Open(str(paths["usd"]))
    assert stage is not None
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == FRAMES - 1
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    obj = int(env.layout.object_body[0])
    prim = stage.GetPrimAtPath(f"/World/env_0/body_{obj}")
    assert prim.IsValid()
    translate = prim.GetAttribute("xformOp:translate")
    assert len(translate.GetTimeSamples()) == FRAMES
    # Frame 0 is the reset state: the box rests on the table, its centre at half its height.
    box_height = env.world_entries[0].extents[2]
    p0 = np.array(translate.Get(0.0))
    np.testing.assert_allclose(p0, start["object_pos"], atol=1e-6)
    assert p0[2] == pytest.approx(0.5 * box_height, abs=0.002)
    # Every hand body animates too: the palm's orient op is sampled per frame.
    palm = int(env.layout.palm_body[0])
    orient = stage.GetPrimAtPath(f"/World/env_0/body_{palm}").GetAttribute("xformOp:orient")
    assert len(orient.GetTimeSamples()) == FRAMES
    # The soft object is a mesh whose points are sampled per frame, starting at the placed nodes.
    soft = UsdGeom.Mesh(stage.GetPrimAtPath("/World/env_1/soft_object"))
    points = soft.GetPointsAttr()
    assert len(points.GetTimeSamples()) == FRAMES
    np.testing.assert_allclose(np.array(points.Get(0.0)), start["particles"], atol=1e-6)
    faces = np.array(soft.GetFaceVertexIndicesAttr().Get())
    assert faces.min() >= 0 and faces.max() < len(start["particles"])


def test_tactile_plot_is_written(rollout):
    import imageio.v3 as iio

    _, paths, _ = rollout
    img = iio.imread(paths["png"])
    assert img.shape[0] > 300 and img.shape[1] > 500
    assert img[..., :3].astype(np.float64).var() > 100.0


def test_size_flag_parses():
    from d3grasp.train.cli_args import make_play_parser

    args = make_play_parser().parse_args(["--checkpoint", "baseline", "--video_size", "320x200"])
    assert args.video_size == (320, 200)
    with pytest.raises(SystemExit):
        make_play_parser().parse_args(["--checkpoint", "baseline", "--video_size", "320"])
