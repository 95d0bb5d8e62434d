"""FastMesh for Blender: send the selected object (or a file) to a FastMesh service and import the clean
mesh beside it.  The sidebar of the 3D view (N) has a FastMesh tab; the service's URL and API key are in the
add-on's preferences.  The network and file work is in :mod:`.client` (no bpy); this module is the UI.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty
from mathutils import Matrix

from . import client

bl_info = {
    "name": "FastMesh",
    "author": "FastMesh",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "3D View > Sidebar (N) > FastMesh",
    "description": "Retopologise the selected object or a file with a FastMesh service",
    "category": "Mesh",
}

DEFAULT = "DEFAULT"  # an enum's "not sent" choice: the service's own default applies
POLL_SECONDS = 0.25  # how often the UI reads the background tasks
MESHLIKE = {"MESH", "CURVE", "SURFACE", "META", "FONT"}  # what evaluates to a mesh


@dataclass
class Running:
    """A job under way: its background task and where its result goes."""

    task: client.Task
    name: str  # the original's name; the result is "<name>_fastmesh"
    offset: tuple[float, float, float]  # added to the imported result's location
    up: str | None  # the up axis asked for (client.up_correction)
    fmt: str  # the result format downloaded: glb, or obj for quads


_running: list[Running] = []
_status = {"text": ""}  # the last finished job's outcome, shown in the panel


def _choice(default_text: str, items) -> list[tuple[str, str, str]]:
    return [(DEFAULT, "Service default", f"Not sent: {default_text}")] + [(v, v.title(), d) for v, d in items]


class FastMeshPreferences(bpy.types.AddonPreferences):
    bl_idname = __name__

    url: StringProperty(name="Service URL", default="http://127.0.0.1:8000",
                        description="Base URL of the FastMesh service (what `make run` prints)")
    api_key: StringProperty(name="API key", subtype="PASSWORD", default="",
                            description="Sent as 'Authorization: Bearer <key>'; empty when the service has no keys")
    timeout: FloatProperty(name="Request timeout (s)", default=60.0, min=1.0, max=3600.0,
                           description="Longest wait for one request's answer (the job itself may run longer)")

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "url")
        col.prop(self, "api_key")
        col.prop(self, "timeout")


class FastMeshSettings(bpy.types.PropertyGroup):
    """The panel's settings (per scene).  Only what the user set is sent, so older services still answer."""

    source: EnumProperty(name="Send", items=[("SELECTED", "Selected object", "The active selected object, "
                                              "modifiers applied, in world space"),
                                             ("FILE", "File", "A mesh or point-cloud file")])
    filepath: StringProperty(name="File", subtype="FILE_PATH")
    use_target_faces: BoolProperty(name="Target faces", description="Ask for a face count")
    # fastmesh.params.TARGET_FACES (the add-on ships without the package; a test checks the two agree)
    target_faces: IntProperty(name="Faces", default=1000, min=4, max=8000)
    topology: EnumProperty(name="Topology", items=_choice("triangles", [
        ("triangle", "Triangles only"), ("quad", "Quad-dominant (downloaded as OBJ: the GLB holds triangles)")]))
    origin: EnumProperty(name="Origin", items=_choice("the input's frame", [
        ("input", "The input's own frame"), ("center", "Pivot at the bounding-box centre"),
        ("bottom", "Pivot at the bottom centre")]))
    use_height: BoolProperty(name="Height", description="Scale the result to this height")
    height: FloatProperty(name="Height", default=1.8, min=1e-4, max=1e5, unit="LENGTH", precision=3)
    up: EnumProperty(name="Up axis", items=_choice("Y", [
        ("y", "Y up (glTF)"), ("z", "Z up in OBJ files (a GLB is always Y up); upright in Blender either way")]))
    closed: EnumProperty(name="Closed", items=_choice("auto", [
        ("auto", "Close when the input is closed"), ("true", "Always close holes"), ("false", "Never close")]))
    uv: BoolProperty(name="UV layout", description="Ask for a UV layout (GLB TEXCOORD_0, OBJ vt)")
    use_seed: BoolProperty(name="Seed", description="Fix the sampling seed")
    seed: IntProperty(name="Seed", default=0, min=0)


def params_of(s: FastMeshSettings) -> dict:
    """The form fields the user set (None: not sent)."""
    def pick(v):
        return None if v == DEFAULT else v
    return {"target_faces": s.target_faces if s.use_target_faces else None, "topology": pick(s.topology),
            "origin": pick(s.origin),
            # Blender stores floats in single precision: send the 6 digits the user typed, not 1.7999999523
            "height": float(f"{s.height:.6g}") if s.use_height else None,
            "up": pick(s.up), "closed": pick(s.closed), "uv": True if s.uv else None,
            "seed": s.seed if s.use_seed else None}


def world_mesh(context, obj) -> tuple[list, list]:
    """``(vertices (V, 3) in world space, polygons)`` of ``obj`` with its modifiers applied."""
    ev = obj.evaluated_get(context.evaluated_depsgraph_get())
    mesh = ev.to_mesh()
    try:
        mw = ev.matrix_world
        return [tuple(mw @ v.co) for v in mesh.vertices], [tuple(p.vertices) for p in mesh.polygons]
    finally:
        ev.to_mesh_clear()


def _selected(context):
    obj = context.active_object
    return obj if obj is not None and obj.select_get() and obj.type in MESHLIKE else None


class FASTMESH_OT_send(bpy.types.Operator):
    """Send the selected object or the chosen file to the FastMesh service; the result is imported beside it"""

    bl_idname = "fastmesh.send"
    bl_label = "Send to FastMesh"

    @classmethod
    def poll(cls, context):
        s = context.scene.fastmesh
        return bool(s.filepath) if s.source == "FILE" else _selected(context) is not None

    def execute(self, context):
        prefs = context.preferences.addons[__name__].preferences
        s = context.scene.fastmesh
        params = params_of(s)
        try:
            c = client.Client(prefs.url, prefs.api_key or None, prefs.timeout)
            client.form_fields(params)  # refuse a bad value here rather than in the thread
            name, filename, data, offset = self._upload(context, s, params)
        except (client.ServiceError, ValueError, OSError) as e:
            self.report({"ERROR"}, f"FastMesh: {e}")
            return {"CANCELLED"}
        fmt = client.import_format(params)
        task = client.Task(c, filename, data, params, fmt=fmt).start()
        _running.append(Running(task, name, offset, params["up"], fmt))
        if not bpy.app.timers.is_registered(tick):
            bpy.app.timers.register(tick, first_interval=POLL_SECONDS)
        self.report({"INFO"}, f"FastMesh: sending {filename}")
        return {"FINISHED"}

    @staticmethod
    def _upload(context, s, params):
        """``(name, filename, bytes, offset of the result)`` of what is sent."""
        if s.source == "FILE":
            path = bpy.path.abspath(s.filepath)
            with open(path, "rb") as f:
                data = f.read()
            filename = os.path.basename(path)
            return os.path.splitext(filename)[0], filename, data, (0.0, 0.0, 0.0)
        obj = _selected(context)
        if obj is None:
            raise ValueError("select a mesh object first")
        vertices, faces = world_mesh(context, obj)
        filename, data = client.upload_of(obj.name, vertices, faces)
        lo, hi = client.bounds(vertices)
        return obj.name, filename, data, client.placement(lo, hi, params.get("origin"))


class FASTMESH_OT_cancel(bpy.types.Operator):
    """Cancel the FastMesh jobs under way (on the service too)"""

    bl_idname = "fastmesh.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return bool(_running)

    def execute(self, context):
        for run in _running:
            run.task.cancel()
        return {"FINISHED"}


def tick() -> float | None:
    """Timer: show the tasks' progress and import the results that arrived (bpy is touched here only, on
    Blender's main thread).  Returns the next interval, or None when nothing is left to watch."""
    for run in list(_running):
        snap = run.task.snapshot()
        if snap["state"] not in ("done", "failed", "cancelled"):
            continue
        _running.remove(run)
        if snap["state"] == "done":
            try:
                with _window_context():
                    names = import_result(run, snap["result"])
                _status["text"] = f"{names[0]}: {snap['message']}"
            except Exception as e:  # a broken file or importer must not kill the timer for the other jobs
                _status["text"] = f"{run.name}: import failed: {str(e)[-200:]}"
                if run.fmt == "glb":
                    # Blender's glTF importer needs numpy, which some Linux builds leave out or ship too new for
                    # it (Debian's 3.4 with numpy 1.24): the same result as OBJ, which Blender reads natively.
                    task = client.Task.download(run.task.client, snap["job"], "obj").start()
                    _running.append(Running(task, run.name, run.offset, run.up, "obj"))
                    _status["text"] = f"{run.name}: the glTF importer failed; fetching the result as OBJ"
        else:
            _status["text"] = f"{run.name}: {snap['message']}"
        print(f"FastMesh: {_status['text']}")
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()
    return POLL_SECONDS if _running else None


def _window_context():
    """A context with a window for the operators a timer calls (a timer runs without one); none in background."""
    windows = bpy.context.window_manager.windows
    if windows and hasattr(bpy.context, "temp_override"):
        return bpy.context.temp_override(window=windows[0])
    return contextlib.nullcontext()


def import_result(run: Running, data: bytes) -> list[str]:
    """Import ``data`` as ``<name>_fastmesh`` beside the original; the new objects' names."""
    fd, path = tempfile.mkstemp(prefix="fastmesh-", suffix=f".{run.fmt}")
    before = {o.name for o in bpy.data.objects}
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        if bpy.context.object is not None and bpy.context.object.mode != "OBJECT":
            bpy.ops.object.mode_set(mode="OBJECT")  # the importers select and link in object mode
        if run.fmt == "glb":
            bpy.ops.import_scene.gltf(filepath=path)
        elif hasattr(bpy.ops.wm, "obj_import"):
            bpy.ops.wm.obj_import(filepath=path)
        else:
            bpy.ops.import_scene.obj(filepath=path)
        new = [o for o in bpy.data.objects if o.name not in before]
        if not new:
            raise ValueError("the result file held no object")
    except Exception:
        for o in [o for o in bpy.data.objects if o.name not in before]:  # what a failed import left behind
            bpy.data.objects.remove(o)
        raise
    finally:
        os.remove(path)
    roots = [o for o in new if o.parent is None or o.parent.name in before]
    move = Matrix.Translation(run.offset) @ Matrix.Rotation(client.up_correction(run.up, run.fmt), 4, "X")
    for o in roots:
        o.matrix_world = move @ o.matrix_world
    new.sort(key=lambda o: (o.type != "MESH", o.name))
    for i, o in enumerate(new):
        o.name = free_name(f"{run.name}_fastmesh" if i == 0 else f"{run.name}_fastmesh_{i}")
        if o.type == "MESH":
            o.data.name = o.name
    return [o.name for o in new]


def free_name(base: str) -> str:
    """``base``, or ``base.001``, ``base.002``, ... when taken.  Given a taken name, Blender 3.4 sometimes
    hands it to the renamed object and renames the one that had it (the earlier result would change name)."""
    name, i = base, 0
    while name in bpy.data.objects:
        i += 1
        name = f"{base}.{i:03d}"
    return name


class VIEW3D_PT_fastmesh(bpy.types.Panel):
    bl_label = "FastMesh"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "FastMesh"

    def draw(self, context):
        s, layout = context.scene.fastmesh, self.layout
        layout.prop(s, "source", expand=True)
        if s.source == "FILE":
            layout.prop(s, "filepath", text="")
        else:
            obj = _selected(context)
            layout.label(text=obj.name if obj else "Select a mesh object", icon="OBJECT_DATA")
        col = layout.column(align=True)
        for flag, value in (("use_target_faces", "target_faces"), ("use_height", "height"), ("use_seed", "seed")):
            row = col.row(align=True)
            row.prop(s, flag)
            sub = row.row(align=True)
            sub.active = getattr(s, flag)
            sub.prop(s, value, text="")
        for name in ("topology", "origin", "up", "closed", "uv"):
            layout.prop(s, name)
        layout.operator(FASTMESH_OT_send.bl_idname, icon="EXPORT")
        for run in _running:
            snap = run.task.snapshot()
            text = f"{run.name}: {snap['message']}"
            if hasattr(layout, "progress"):  # Blender 4.0+
                layout.progress(factor=snap["fraction"], type="BAR", text=text)
            else:
                layout.label(text=f"{text} ({snap['fraction']:.0%})", icon="TIME")
        if _running:
            layout.operator(FASTMESH_OT_cancel.bl_idname, icon="CANCEL")
        if _status["text"]:
            layout.label(text=_status["text"], icon="INFO")


CLASSES = (FastMeshPreferences, FastMeshSettings, FASTMESH_OT_send, FASTMESH_OT_cancel, VIEW3D_PT_fastmesh)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.fastmesh = PointerProperty(type=FastMeshSettings)


def unregister():
    for run in _running:
        run.task.cancel()
    _running.clear()
    if bpy.app.timers.is_registered(tick):
        bpy.app.timers.unregister(tick)
    del bpy.types.Scene.fastmesh
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
