"""Run by ``test_blender.py`` in a process of its own: import a stage with Blender's USD importer,
colour each instance's mesh by the emission colour the job gives it (the rest black), render
with Cycles from the job's camera (OpenCV axes, pixel centres at ``u + 0.5``), and write the
render, the imported scene meshes' vertices in world coordinates and a report (with the materials the importer gave each instance).

Usage: ``python blender_render.py JOB.json`` (keys: stage, K, width, height, camera_to_world,
colors {instance: rgb}, places {instance: translation}, png, scene_points, report; optionally
alone {instance: png}: each instance rendered again with nothing else).
"""

from __future__ import annotations

import json
import sys

import bpy
import mathutils
import numpy as np


def emission(name: str, rgb: tuple[float, float, float]) -> bpy.types.Material:
    """A material that shows ``rgb`` whatever the light."""
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    nodes = m.node_tree.nodes
    nodes.clear()
    out, em = nodes.new("ShaderNodeOutputMaterial"), nodes.new("ShaderNodeEmission")
    em.inputs["Color"].default_value = (*rgb, 1.0)
    m.node_tree.links.new(em.outputs[0], out.inputs[0])
    return m


def main(job: dict) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=job["stage"], support_scene_instancing=False)
    scene = bpy.context.scene
    meshes = [o for o in scene.objects if o.type == "MESH"]

    def instance_of(o: bpy.types.Object) -> str | None:
        """The instance whose place (its similarity's translation) the object stands at: Blender
        folds an Xform with one child into that child, so prim names do not survive the import."""
        t = np.array(o.matrix_world)[:3, 3]
        name = min(job["places"], key=lambda n: np.linalg.norm(np.asarray(job["places"][n]) - t))
        return name if np.linalg.norm(np.asarray(job["places"][name]) - t) < 1e-4 else None

    looks = {}  # what the importer made of each instance's materials, before they are replaced
    for o in meshes:
        inst = instance_of(o)
        if inst is None:
            continue
        found = looks.setdefault(inst, {"vertices": len(o.data.vertices), "colors": [], "images": []})
        for m in o.data.materials:
            nodes = m.node_tree.nodes if m and m.use_nodes else []
            for node in nodes:
                if node.type == "BSDF_PRINCIPLED" and not node.inputs["Base Color"].is_linked:
                    found["colors"].append(list(node.inputs["Base Color"].default_value)[:3])
                if node.type == "TEX_IMAGE" and node.image is not None:
                    found["images"].append(list(node.image.size))

    black = emission("black", tuple(job.get("rest_color", (0.0, 0.0, 0.0))))
    mats = {name: emission(name, tuple(rgb)) for name, rgb in job["colors"].items()}
    for o in meshes:
        inst = instance_of(o)
        o.data = o.data.copy()  # instances of one object may share their mesh data
        o.data.materials.clear()
        o.data.materials.append(mats[inst] if inst else black)

    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(cam)
    K, w, h = np.asarray(job["K"]), int(job["width"]), int(job["height"])
    # OpenCV camera axes (x right, y down, z forward) -> Blender's (y up, looking along -z).
    c2w = np.asarray(job["camera_to_world"]) @ np.diag([1.0, -1.0, -1.0, 1.0])
    cam.matrix_world = mathutils.Matrix([list(r) for r in c2w])  # rows (a plain list would be columns)
    cam.data.sensor_fit, cam.data.sensor_width = "HORIZONTAL", 36.0
    cam.data.lens = K[0, 0] * 36.0 / w
    cam.data.shift_x, cam.data.shift_y = (w / 2 - K[0, 2]) / w, (K[1, 2] - h / 2) / w
    scene.camera = cam
    scene.render.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_denoising = "CPU", 4, False
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.filter_width, scene.cycles.max_bounces = 0.01, 0
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = w, h, 100
    scene.view_settings.view_transform = "Standard"
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.0, 0.0, 0.0)
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = job["png"]
    bpy.ops.render.render(write_still=True)
    # Each instance alone (``alone``: instance -> png): its whole silhouette, nothing in front.
    for name, png in job.get("alone", {}).items():
        for o in meshes:
            o.hide_render = instance_of(o) != name
        scene.render.filepath = png
        bpy.ops.render.render(write_still=True)
    for o in meshes:
        o.hide_render = False

    rest = [o for o in meshes if instance_of(o) is None]
    points = [np.array([tuple(v.co) for v in o.data.vertices]) @ np.array(o.matrix_world)[:3, :3].T
              + np.array(o.matrix_world)[:3, 3] for o in rest]
    np.save(job["scene_points"], np.concatenate(points) if points else np.zeros((0, 3)))
    report = {"instances": sorted(n for n in (instance_of(o) for o in meshes) if n),
              "scene_meshes": sorted(o.name for o in rest), "looks": looks}
    with open(job["report"], "w") as f:
        json.dump(report, f)


if __name__ == "__main__":
    with open(sys.argv[1]) as f:
        main(json.load(f))
