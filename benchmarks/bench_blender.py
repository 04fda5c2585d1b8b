"""The Blender Cycles bridge against Cycles rendering the same samples in one render.

For three scenes built here in bpy (a textured floor, a glass sphere, depth of field), at 128x128 and
32 spp on the CPU: the wall time of `mcrecon blender log` (one subset render per sample index, plus
the probe renders of the film positions) against Cycles' own 32-spp render, and the relative MSE
against a 1024-spp Cycles render of the log's pixel means, of Cycles' own 32-spp render with the same
seed and with another seed (the seed-to-seed spread), and what 32 independent samples of the same
per-sample variance would give (the log's per-pixel variance over 32).

    python benchmarks/bench_blender.py [--size 128] [--spp 32] [--ref-spp 1024] [--threads 2]

Needs bpy (pip install 'mcrecon[blender]').
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from mcrecon.io import read_log
from mcrecon.renderers import blender as bl


def _material(bpy, name, *, color=(0.8, 0.8, 0.8), glass=False, checker=None):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nt = m.node_tree
    if glass:
        nt.nodes.clear()
        g = nt.nodes.new("ShaderNodeBsdfGlass")
        g.inputs["IOR"].default_value = 1.5
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(g.outputs[0], out.inputs[0])
        return m
    p = nt.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (*color, 1)
    if checker is not None:
        c = nt.nodes.new("ShaderNodeTexChecker")
        c.inputs["Scale"].default_value = checker
        c.inputs["Color1"].default_value = (0.9, 0.8, 0.2, 1)
        c.inputs["Color2"].default_value = (0.1, 0.2, 0.6, 1)
        n = nt.nodes.new("ShaderNodeTexNoise")
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.inputs["Factor"].default_value = 0.3
        nt.links.new(c.outputs["Color"], mix.inputs[6])
        nt.links.new(n.outputs["Color"], mix.inputs[7])
        nt.links.new(mix.outputs[2], p.inputs["Base Color"])
    return m


def build(kind: str, path: Path, *, size: int, seed: int) -> None:
    """Save scene ``kind`` (textures, glass, dof) with Cycles seed ``seed`` to ``path``."""
    bpy = bl._bpy()
    with bl._quiet():
        bpy.ops.wm.read_factory_settings(use_empty=True)
        sc = bpy.context.scene
        sc.render.resolution_x = sc.render.resolution_y = size
        sc.render.resolution_percentage = 100
        sc.cycles.seed = seed
        sc.cycles.max_bounces = 8
        world = bpy.data.worlds.new("w")
        world.use_nodes = True
        world.node_tree.nodes["Background"].inputs[0].default_value = (0.3, 0.35, 0.45, 1)
        sc.world = world
        cam = bpy.data.cameras.new("cam")
        co = bpy.data.objects.new("cam", cam)
        sc.collection.objects.link(co)
        sc.camera = co
        co.location, co.rotation_euler = (0, -6, 2.5), (1.2, 0, 0)
        bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, 0))
        floor = bpy.context.object
        floor.data.materials.append(_material(bpy, "floor", checker=12.0))
        light = bpy.data.lights.new("area", "AREA")
        light.energy, light.size = 600, 1.5
        lo = bpy.data.objects.new("area", light)
        lo.location, lo.rotation_euler = (2, -2, 4), (0.5, 0.3, 0)
        sc.collection.objects.link(lo)
        if kind == "glass":
            bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, location=(0, 0, 1.0), segments=48, ring_count=24)
            bpy.ops.object.shade_smooth()
            bpy.context.object.data.materials.append(_material(bpy, "glass", glass=True))
        elif kind == "dof":
            for i, (x, y) in enumerate(((-1.8, -2.5), (0, 0), (1.8, 3.5))):
                bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7, location=(x, y, 0.7))
                bpy.context.object.data.materials.append(
                    _material(bpy, f"s{i}", color=((0.8, 0.2, 0.2), (0.2, 0.8, 0.2), (0.2, 0.3, 0.9))[i]))
            cam.dof.use_dof, cam.dof.aperture_fstop = True, 0.4
            cam.dof.focus_distance = float(np.linalg.norm(np.array(co.location) - np.array((0, 0, 0.7))))
        bpy.ops.wm.save_as_mainfile(filepath=str(path))


def rel_mse(img, ref) -> float:
    return float(np.mean((img - ref) ** 2 / (ref ** 2 + 1e-2)))


def log_stats(path):
    lg = read_log(path)
    c = lg.read_all()
    idx = np.floor(c.positions[:, 1]).astype(int) * lg.width + np.floor(c.positions[:, 0]).astype(int)
    n = np.bincount(idx, minlength=lg.width * lg.height)[:, None]
    v = c.values.astype(np.float64)
    s1 = np.stack([np.bincount(idx, weights=v[:, k], minlength=n.size) for k in range(3)], 1) / n
    s2 = np.stack([np.bincount(idx, weights=v[:, k] ** 2, minlength=n.size) for k in range(3)], 1) / n
    shape = (lg.height, lg.width, 3)
    return s1.reshape(shape), (np.maximum(s2 - s1 ** 2, 0) * n / np.maximum(n - 1, 1)).reshape(shape)


def render_args(ap: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The film, budget, reference and Cycles threads every Blender benchmark takes."""
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2)
    return ap


def main() -> None:
    ap = render_args(argparse.ArgumentParser(description=__doc__.splitlines()[0]))
    a = ap.parse_args()
    if not bl.bpy_available():
        raise SystemExit(bl.BPY_MISSING)
    print(f"{a.size}x{a.size}, {a.spp} spp, {a.threads} threads, reference {a.ref_spp} spp; relMSE = mean((x - ref)^2 "
          "/ (ref^2 + 0.01))")
    print("| scene | log wall (s) | Cycles' render (s) | ratio | log relMSE | Cycles' relMSE (same seed / other seed) "
          "| independent samples' relMSE (expected) |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for kind in ("textures", "glass", "dof"):
            for seed in (0, 1):
                build(kind, tmp / f"{kind}{seed}.blend", size=a.size, seed=seed)
            s0 = tmp / f"{kind}0.blend"
            ref, _ = bl.render_reference(s0, spp=a.ref_spp, threads=a.threads)
            bl.render_reference(s0, spp=1, threads=a.threads)  # the same warm-up before each timing
            t = time.perf_counter()
            own0, _ = bl.render_reference(s0, spp=a.spp, threads=a.threads)
            t_own = time.perf_counter() - t
            own1, _ = bl.render_reference(tmp / f"{kind}1.blend", spp=a.spp, threads=a.threads)
            t = time.perf_counter()
            bl.dump_cycles_log(tmp / f"{kind}.h5", s0, spp=a.spp, threads=a.threads, features="all")
            t_log = time.perf_counter() - t
            mean, var = log_stats(tmp / f"{kind}.h5")
            indep = float(np.mean(var / a.spp / (ref ** 2 + 1e-2)))
            print(f"| {kind} | {t_log:.1f} | {t_own:.1f} | {t_log / t_own:.1f}x | {rel_mse(mean, ref):.2e} | "
                  f"{rel_mse(own0, ref):.2e} / {rel_mse(own1, ref):.2e} | {indep:.2e} |", flush=True)


if __name__ == "__main__":
    main()
