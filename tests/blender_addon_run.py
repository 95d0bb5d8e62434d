"""Run inside Blender by tests/test_blender_client.py::test_addon_in_blender: install the add-on from the zip
$FASTMESH_ZIP, send the default cube with several settings, and a file, to the stub service $FASTMESH_STUB
through the panel's operators, and print what the add-on imported and drew as one ``RESULT <json>`` line.

Background mode has no event loop, so the timer the operator registers never fires: the script calls the same
``tick`` the timer calls until no job is left.
"""

import json
import os
import sys
import tempfile
import time

import bpy

ICONS = set(bpy.types.UILayout.bl_rna.functions["label"].parameters["icon"].enum_items.keys())


class CheckingLayout:
    """Stands in for the panel's UILayout, which background mode has none of: checks every property, operator
    and icon the panel names (a real layout only prints a warning for a wrong one) and records what is drawn."""

    def __init__(self):
        self.drawn = []
        self.active = True

    def row(self, **kw):
        return self

    column = row

    def prop(self, data, name, **kw):
        assert name in data.bl_rna.properties.keys(), f"no property {name}"
        self.drawn.append(("prop", name))

    def operator(self, idname, icon="NONE", **kw):
        module, name = idname.split(".")
        assert name in dir(getattr(bpy.ops, module)) and icon in ICONS, (idname, icon)
        self.drawn.append(("operator", idname))

    def label(self, text="", icon="NONE"):
        assert icon in ICONS, icon
        self.drawn.append(("label", text))

    if "progress" in bpy.types.UILayout.bl_rna.functions:  # Blender 4.0+; the panel draws a label in older ones
        def progress(self, factor=0.0, type="BAR", text=""):
            assert 0.0 <= factor <= 1.0 and type in ("BAR", "RING"), (factor, type)
            self.drawn.append(("progress", text))


def draw(addon) -> list:
    layout = CheckingLayout()
    addon.VIEW3D_PT_fastmesh.draw(type("Panel", (), {"layout": layout})(), bpy.context)
    return layout.drawn


def send(addon, select=None, cancel=False) -> list:
    """Send with the panel's settings, run the timer's tick until the job is imported; what the panel drew
    while the job ran."""
    if select is not None:  # the importer selects what it imported: select the original again
        for o in bpy.context.selected_objects:
            o.select_set(False)
        select.select_set(True)
        bpy.context.view_layer.objects.active = select
    assert bpy.ops.fastmesh.send() == {"FINISHED"}
    assert addon._running and bpy.app.timers.is_registered(addon.tick)
    while addon._running[0].task.snapshot()["stage"] is None:  # until the service answered the upload
        time.sleep(0.01)
    drawn = draw(addon)
    if cancel:
        assert bpy.ops.fastmesh.cancel() == {"FINISHED"}
    deadline = time.monotonic() + 30
    while addon._running and time.monotonic() < deadline:
        addon.tick()
        time.sleep(0.02)
    assert not addon._running, "the job did not finish"
    return drawn


def facts(obj) -> dict:
    pts = [obj.matrix_world @ v.co for v in obj.data.vertices]
    return {"min": [min(p[i] for p in pts) for i in range(3)], "max": [max(p[i] for p in pts) for i in range(3)],
            "location": list(obj.location), "polygon_sizes": sorted(len(p.vertices) for p in obj.data.polygons),
            "name": obj.name}


def gltf_works() -> bool:
    """Whether this Blender's glTF importer reads a valid GLB ($FASTMESH_GLB): Debian's 3.4 fails on numpy 1.24."""
    before = set(bpy.data.objects.keys())
    try:
        bpy.ops.import_scene.gltf(filepath=os.environ["FASTMESH_GLB"])
        return True
    except Exception:  # noqa: BLE001 -- any failure of the importer
        return False
    finally:
        for name in set(bpy.data.objects.keys()) - before:
            bpy.data.objects.remove(bpy.data.objects[name])


def main() -> None:
    bpy.ops.preferences.addon_install(filepath=os.environ["FASTMESH_ZIP"])
    bpy.ops.preferences.addon_enable(module="fastmesh_blender")
    addon = sys.modules["fastmesh_blender"]
    addon.client.POLL_SECONDS = 0.02  # the stub answers at once: no need to wait half a second a read
    prefs = bpy.context.preferences.addons["fastmesh_blender"].preferences
    prefs.url, prefs.api_key = os.environ["FASTMESH_STUB"], "sekrit"
    cube = bpy.data.objects["Cube"]
    cube.location, cube.scale = (5, 1, 2), (1, 2, 3)
    bpy.context.view_layer.update()
    s = bpy.context.scene.fastmesh
    faces = s.bl_rna.properties["target_faces"]
    out = {"gltf_works": gltf_works(), "target_faces_range": [faces.hard_min, faces.hard_max]}

    s.use_target_faces, s.target_faces, s.origin = True, 500, "bottom"
    out["drawn_running"] = send(addon, cube)
    out["drawn_done"] = draw(addon)
    out["Cube_fastmesh"] = facts(bpy.data.objects["Cube_fastmesh"])

    s.use_target_faces, s.origin, s.topology, s.use_height, s.height = False, "DEFAULT", "quad", True, 1.8
    send(addon, cube)
    out["Cube_fastmesh.001"] = facts(bpy.data.objects["Cube_fastmesh.001"])

    s.topology, s.use_height = "DEFAULT", False
    path = os.path.join(tempfile.mkdtemp(), "box.obj")
    with open(path, "w") as f:
        f.write("".join(f"v {x} {y} {z}\n" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)))
        f.write("f 1 2 4 3\nf 5 7 8 6\nf 1 5 6 2\nf 3 4 8 7\nf 1 3 7 5\nf 2 6 8 4\n")
    s.source, s.filepath = "FILE", path
    send(addon)
    out["file"] = facts(bpy.data.objects["box_fastmesh"])

    s.source, s.use_seed, s.seed = "SELECTED", True, 13  # the stub fails this seed
    send(addon, cube)
    out["failed"] = addon._status["text"]

    s.seed = 7  # the stub's GLB for this seed is broken: the add-on falls back to the OBJ
    send(addon, cube)
    out["fallback"] = facts(bpy.data.objects["Cube_fastmesh.002"])

    s.use_seed, s.topology, s.origin, s.up, s.uv = False, "quad", "center", "z", True
    send(addon, cube)
    out["Cube_fastmesh.003"] = facts(bpy.data.objects["Cube_fastmesh.003"])

    s.use_seed, s.seed, s.topology, s.origin, s.up, s.uv = True, 99, "DEFAULT", "DEFAULT", "DEFAULT", False
    # a job the stub runs for ever: cancelled from the panel
    send(addon, cube, cancel=True)
    out["cancelled"] = addon._status["text"]
    print("RESULT " + json.dumps(out))


main()
