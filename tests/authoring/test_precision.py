"""Authored numbers at a stated precision: what is rounded, what is left alone."""

from __future__ import annotations

import json
import math

from d3grasp.authoring.precision import (
    export_layer,
    stable_float,
    stable_floats,
    stable_json,
    stable_usda_text,
)


def test_stable_floats_nine_digits_on_a_grid_relative_to_the_tuple() -> None:
    assert stable_float(0.07339999999999999) == 0.0734
    assert stable_float(-0.003219999999999997) == -0.00322
    assert stable_float(0.9999999999865076) == 1.0
    assert stable_float(1234.56789012345) == 1234.56789
    assert stable_float(1.2104267466e-5) == 1.21042675e-5  # a lone small number keeps 9 digits
    # A quaternion component from a cancellation keeps only what is above 1e-12 of the tuple.
    q = [0.7070975962551216, -0.000005211686410533155, -1.732268032805893e-8, -0.7071159655396263]
    q_other_cpu = [0.7070975962551216, -0.000005211686410533156, -1.7322680328058934e-8, -0.7071159655396263]
    assert (
        stable_floats(q)
        == stable_floats(q_other_cpu)
        == [0.707097596, -5.2116864e-6, -1.73227e-8, -0.707115966]
    )
    assert stable_floats([1.94e-7, 4.2708333e-8, 2.2170967e-7]) == [1.94e-7, 4.2708333e-8, 2.2170967e-7]
    assert stable_float(3.5813046e-19) == 0.0 and math.copysign(1.0, stable_float(-3e-19)) == 1.0
    assert stable_floats([0.0, 0.0, -3.5813046e-19]) == [0.0, 0.0, 0.0]
    assert math.isnan(stable_float(math.nan)) and stable_float(math.inf) == math.inf
    # Values a few ulps apart land on the same number.
    x = 0.11795956546164
    assert stable_float(x) == stable_float(math.nextafter(x, 1.0)) == stable_float(math.nextafter(x, 0.0))


def test_stable_json_rounds_floats_only() -> None:
    doc = {"mass": 0.1329766447278717, "n": 3, "ids": ["a1.5", 2], "ext": [0.18968725949525833, 1e-14, 2]}
    assert stable_json(doc) == {"mass": 0.132976645, "n": 3, "ids": ["a1.5", 2], "ext": [0.189687259, 0.0, 2]}
    assert stable_json({"flag": True, "pair": (True, 0.30000000000000004)}) == {
        "flag": True,
        "pair": [True, 0.3],
    }
    json.dumps(stable_json(doc))


def test_usda_text_numbers_rounded_strings_names_and_comments_kept() -> None:
    text = "\n".join(
        [
            "#usda 1.0",
            "(",
            '    doc = """version 0.1.0 at 1.23456789012345"""',
            ")",
            'def Mesh "hull_000" (prepend apiSchemas = ["PhysicsCollisionAPI"])',
            "{",
            "    double3 xformOp:scale = (0.13778, 0.1029, 0.07339999999999999)",
            "    point3f[] points = [(-0, 1e-20, 2.5E-3), (1, 2, 3)]",
            "    int count = -0",
            '    string note = "keep 0.30000000000000004 and 1e-20"',
            "    asset file = @./meshes/part_1.5.usd@",
            "    rel target = </root/body_2.attr>",
            "}",
        ]
    )
    out = stable_usda_text(text).splitlines()
    assert out[0] == "#usda 1.0"
    assert out[2] == '    doc = """version 0.1.0 at 1.23456789012345"""'
    assert out[4] == 'def Mesh "hull_000" (prepend apiSchemas = ["PhysicsCollisionAPI"])'
    assert out[6] == "    double3 xformOp:scale = (0.13778, 0.1029, 0.0734)"
    assert out[7] == "    point3f[] points = [(0, 0.0, 0.0025), (1, 2, 3)]"  # tuples: one grid each
    assert out[8] == "    int count = 0"
    assert out[9:12] == [
        '    string note = "keep 0.30000000000000004 and 1e-20"',
        "    asset file = @./meshes/part_1.5.usd@",
        "    rel target = </root/body_2.attr>",
    ]


def test_export_layer_writes_the_rounded_values(tmp_path) -> None:
    from pxr import Gf, Sdf, Usd

    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/box", "Xform")
    prim.CreateAttribute("d", Sdf.ValueTypeNames.Double).Set(0.07339999999999999)
    prim.CreateAttribute("q", Sdf.ValueTypeNames.Quatd).Set(Gf.Quatd(0.9999999999865076, 1e-19, 0, 0))
    for name in ("box.usda", "box.usdc"):
        export_layer(stage.GetRootLayer(), str(tmp_path / name))
        reread = Usd.Stage.Open(str(tmp_path / name))
        back = reread.GetPrimAtPath("/box")
        assert back.GetAttribute("d").Get() == 0.0734
        q = back.GetAttribute("q").Get()
        assert q.GetReal() == 1.0 and tuple(q.GetImaginary()) == (0.0, 0.0, 0.0)
