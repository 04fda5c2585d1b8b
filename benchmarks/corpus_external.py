"""The corpus's Mitsuba 3 and Blender Cycles scenes, built programmatically (no files to download).

:mod:`corpus` lists them and caches their logs and references; this module
only says what each scene is.  Cycles scenes are saved as ``.blend`` files
(bpy 4.5); Mitsuba scenes are scene dictionaries.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_blender import _material  # noqa: E402  (the glass material of the Blender bench's scenes)

#: Cycles scenes: name -> one line.
CYCLES_SCENES = {
    "studio": "a small bright light over glass and metal spheres on a textured floor: caustics, glossy paths",
    "dof": "three spheres over a checker and noise floor, thin lens focused on the middle one",
    "window": "a closed room lit only through a window by a sun: indirect light on most of the walls",
    "fence": "a thin wire fence (a wireframe grid) before a brick wall, a soft area light",
    "glossy_hdr": "glossy metal and a sharp-highlight floor under a tiny, very bright light: HDR highlights",
}

#: Mitsuba scenes: name -> one line (the first three are those of benchmarks/mitsuba_textured.py).
MITSUBA_SCENES = {
    "floor_spheres": "a texel floor and checker tiles, a glass and a metal sphere, one small spherical light",
    "thin_lens": "a thin-lens camera focused on a checker card before a plane of random texels",
    "wall_floor": "a checker wall and floor, a diffuse sphere's soft shadow from a rectangular light",
    "cbox": "the Cornell box (Mitsuba's built-in dictionary), path tracing at depth 6",
}


# ----------------------------------------------------------------------------
# Cycles
# ----------------------------------------------------------------------------

def _principled(bpy, name, *, color=(0.8, 0.8, 0.8), roughness=0.5, metallic=0.0):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    p = m.node_tree.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (*color, 1)
    p.inputs["Roughness"].default_value = roughness
    p.inputs["Metallic"].default_value = metallic
    return m, p


def _textured(bpy, name, *, scale=12.0, c1=(0.9, 0.8, 0.2), c2=(0.1, 0.2, 0.6), noise=0.3, roughness=0.5):
    """A checker mixed with coloured noise (texture detail at two scales)."""
    m, p = _principled(bpy, name, roughness=roughness)
    nt = m.node_tree
    c = nt.nodes.new("ShaderNodeTexChecker")
    c.inputs["Scale"].default_value = scale
    c.inputs["Color1"].default_value = (*c1, 1)
    c.inputs["Color2"].default_value = (*c2, 1)
    n = nt.nodes.new("ShaderNodeTexNoise")
    n.inputs["Scale"].default_value = 3.0 * scale
    mix = nt.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.inputs["Factor"].default_value = noise
    nt.links.new(c.outputs["Color"], mix.inputs[6])
    nt.links.new(n.outputs["Color"], mix.inputs[7])
    nt.links.new(mix.outputs[2], p.inputs["Base Color"])
    return m


def _brick(bpy, name):
    m, p = _principled(bpy, name, roughness=0.8)
    nt = m.node_tree
    b = nt.nodes.new("ShaderNodeTexBrick")
    b.inputs["Scale"].default_value = 6.0
    b.inputs["Color1"].default_value = (0.55, 0.22, 0.12, 1)
    b.inputs["Color2"].default_value = (0.35, 0.15, 0.10, 1)
    b.inputs["Mortar"].default_value = (0.75, 0.73, 0.70, 1)
    nt.links.new(b.outputs["Color"], p.inputs["Base Color"])
    return m


def _world(bpy, sc, color, strength=1.0):
    world = bpy.data.worlds.new("w")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs[0].default_value = (*color, 1)
    bg.inputs[1].default_value = strength
    sc.world = world


def _camera(bpy, sc, location, rotation, lens=50.0):
    cam = bpy.data.cameras.new("cam")
    cam.lens = lens
    co = bpy.data.objects.new("cam", cam)
    sc.collection.objects.link(co)
    sc.camera = co
    co.location, co.rotation_euler = location, rotation
    return cam, co


def _light(bpy, sc, kind, energy, location, rotation=(0, 0, 0), size=None):
    light = bpy.data.lights.new(kind.lower(), kind)
    light.energy = energy
    if size is not None:
        if kind == "AREA":
            light.size = size
        elif kind == "SUN":
            light.angle = size
        else:
            light.shadow_soft_size = size
    lo = bpy.data.objects.new(kind.lower(), light)
    lo.location, lo.rotation_euler = location, rotation
    sc.collection.objects.link(lo)
    return light


def _box(bpy, name, location, scale, material):
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=location)
    o = bpy.context.object
    o.name = name
    o.scale = scale
    o.data.materials.append(material)
    return o


def build_cycles(name: str, path: Path, *, size: int, seed: int) -> None:
    """Save Cycles scene ``name`` at ``size`` x ``size`` with Cycles seed ``seed`` to ``path``."""
    from mcrecon.renderers import blender as bl

    if name not in CYCLES_SCENES:
        raise SystemExit(f"unknown Cycles scene {name!r}; valid: {', '.join(CYCLES_SCENES)}")
    bpy = bl._bpy()
    with bl._quiet():
        bpy.ops.wm.read_factory_settings(use_empty=True)
        sc = bpy.context.scene
        sc.render.engine = "CYCLES"
        sc.render.resolution_x = sc.render.resolution_y = size
        sc.render.resolution_percentage = 100
        sc.cycles.seed = seed
        sc.cycles.max_bounces = 6
        if name in ("studio", "dof", "glossy_hdr"):
            _world(bpy, sc, (0.3, 0.35, 0.45), 0.15 if name != "dof" else 1.0)
            cam, co = _camera(bpy, sc, (0, -6, 2.5), (1.2, 0, 0))
            bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, 0))
            floor = bpy.context.object
            if name == "glossy_hdr":
                m, _ = _principled(bpy, "floor", color=(0.2, 0.2, 0.22), roughness=0.08)
                floor.data.materials.append(m)
            else:
                floor.data.materials.append(_textured(bpy, "floor", scale=12.0))
        if name == "studio":
            _light(bpy, sc, "POINT", 900, (1.5, -1.0, 4.0), size=0.05)
            bpy.ops.mesh.primitive_uv_sphere_add(radius=0.9, location=(-1.0, 0, 0.9), segments=48, ring_count=24)
            bpy.ops.object.shade_smooth()
            bpy.context.object.data.materials.append(_material(bpy, "glass", glass=True))
            bpy.ops.mesh.primitive_uv_sphere_add(radius=0.8, location=(1.2, 0.8, 0.8), segments=48, ring_count=24)
            bpy.ops.object.shade_smooth()
            bpy.context.object.data.materials.append(
                _principled(bpy, "metal", color=(0.95, 0.7, 0.35), roughness=0.15, metallic=1.0)[0])
        elif name == "dof":
            _light(bpy, sc, "AREA", 600, (2, -2, 4), (0.5, 0.3, 0), size=1.5)
            for i, (x, y) in enumerate(((-1.8, -2.5), (0, 0), (1.8, 3.5))):
                bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7, location=(x, y, 0.7))
                bpy.ops.object.shade_smooth()
                bpy.context.object.data.materials.append(
                    _textured(bpy, f"s{i}", scale=6.0, c1=((0.8, 0.2, 0.2), (0.2, 0.8, 0.2), (0.2, 0.3, 0.9))[i],
                              c2=(0.9, 0.9, 0.85), noise=0.2))
            cam.dof.use_dof, cam.dof.aperture_fstop = True, 0.4
            cam.dof.focus_distance = float(np.linalg.norm(np.array(co.location) - np.array((0, 0, 0.7))))
        elif name == "glossy_hdr":
            _light(bpy, sc, "POINT", 4000, (-1.5, 1.5, 5.0), size=0.02)
            _light(bpy, sc, "AREA", 40, (3, -3, 3), (0.8, 0.0, 0.8), size=2.0)
            for i, (x, y, r) in enumerate(((-1.3, 0.2, 0.8), (0.6, -0.6, 0.5), (1.6, 1.2, 0.9))):
                bpy.ops.mesh.primitive_uv_sphere_add(radius=r, location=(x, y, r), segments=48, ring_count=24)
                bpy.ops.object.shade_smooth()
                bpy.context.object.data.materials.append(
                    _principled(bpy, f"m{i}", color=((0.9, 0.9, 0.92), (0.95, 0.6, 0.3), (0.6, 0.7, 0.9))[i],
                                roughness=(0.05, 0.25, 0.12)[i], metallic=1.0)[0])
        elif name == "window":
            _world(bpy, sc, (0.5, 0.6, 0.8), 1.0)
            wall = _principled(bpy, "wall", color=(0.75, 0.72, 0.68), roughness=0.9)[0]
            floor_m = _textured(bpy, "floor", scale=10.0, c1=(0.55, 0.35, 0.2), c2=(0.35, 0.22, 0.12), noise=0.4)
            # a 6 x 6 x 3 room: floor, ceiling, three walls, and a front wall (x = 3) with a window hole
            _box(bpy, "floor", (0, 0, -0.05), (6.2, 6.2, 0.1), floor_m)
            _box(bpy, "ceiling", (0, 0, 3.05), (6.2, 6.2, 0.1), wall)
            _box(bpy, "back", (-3.05, 0, 1.5), (0.1, 6.2, 3.2), wall)
            _box(bpy, "left", (0, 3.05, 1.5), (6.2, 0.1, 3.2), wall)
            _box(bpy, "right", (0, -3.05, 1.5), (6.2, 0.1, 3.2), wall)
            # the window wall (x = 3.05) in four pieces around a 1.6 x 1.2 hole centred at (y 0.6, z 1.7)
            _box(bpy, "w_low", (3.05, 0, 0.55), (0.1, 6.2, 1.1), wall)
            _box(bpy, "w_high", (3.05, 0, 2.65), (0.1, 6.2, 0.7), wall)
            _box(bpy, "w_l", (3.05, -1.6, 1.7), (0.1, 2.8, 1.2), wall)
            _box(bpy, "w_r", (3.05, 2.5, 1.7), (0.1, 1.2, 1.2), wall)
            _box(bpy, "table", (-1.0, -0.5, 0.4), (1.2, 0.8, 0.8), _principled(bpy, "t", color=(0.3, 0.5, 0.7))[0])
            sun = _light(bpy, sc, "SUN", 120.0, (8, 2, 6), size=math.radians(1.0))
            lo = bpy.data.objects["sun"]
            lo.rotation_euler = (0.0, math.radians(55), math.radians(10))  # travelling towards -x, into the room
            sun.angle = math.radians(1.0)
            # the camera inside, in the corner by the window, looking at the back wall the sun does not reach
            _camera(bpy, sc, (2.6, -2.5, 1.6), (math.radians(88), 0, math.radians(125)), lens=20.0)
        elif name == "fence":
            _world(bpy, sc, (0.6, 0.7, 0.85), 0.6)
            _camera(bpy, sc, (0, -6, 1.5), (math.radians(90), 0, 0), lens=45.0)
            _box(bpy, "wall", (0, 1.5, 1.5), (8.0, 0.2, 5.0), _brick(bpy, "brick"))
            bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, 0))
            bpy.context.object.data.materials.append(_principled(bpy, "ground", color=(0.35, 0.33, 0.3))[0])
            bpy.ops.mesh.primitive_grid_add(x_subdivisions=60, y_subdivisions=40, size=6.0, location=(0, -2.0, 1.5),
                                            rotation=(math.radians(90), 0, math.radians(0)))
            fence = bpy.context.object
            fence.rotation_euler = (math.radians(90), math.radians(45), 0)
            mod = fence.modifiers.new("wire", "WIREFRAME")
            mod.thickness = 0.012
            fence.data.materials.append(_principled(bpy, "wire", color=(0.6, 0.6, 0.62), roughness=0.3,
                                                    metallic=1.0)[0])
            _light(bpy, sc, "AREA", 500, (2.5, -5, 4), (0.8, 0.0, 0.5), size=2.5)
        bpy.ops.wm.save_as_mainfile(filepath=str(path))


# ----------------------------------------------------------------------------
# Mitsuba 3
# ----------------------------------------------------------------------------

def build_mitsuba(name: str, size: int) -> dict:
    """The Mitsuba scene dict of ``name`` at ``size`` x ``size``."""
    if name not in MITSUBA_SCENES:
        raise SystemExit(f"unknown Mitsuba scene {name!r}; valid: {', '.join(MITSUBA_SCENES)}")
    if name == "cbox":
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
        d = mi.cornell_box()
        d["integrator"] = {"type": "path", "max_depth": 6}
        d["sensor"]["film"] = {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}
        return d
    from mitsuba_textured import build_scene

    return build_scene(name, size)
