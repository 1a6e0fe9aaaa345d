"""Export Spike Dataset: a Blender 4.2+ extension that writes spike-camera datasets (SpikeNeRF).

File > Export > Spike Dataset, or the "Spike Dataset" panel (Properties > Output). The current
scene is rendered through its active camera on the NeRF rig (the object is assumed at the
origin), then converted by the project's own generator (the ``spikegen`` package, shipped as a
wheel inside the extension) into ``<directory>/<name>_i<I>/`` for each intensity: the same
export code as ``spikegen render``.

Interactive use runs as a modal operator: one image per timer tick, a progress bar, Esc
cancels (the view being rendered is removed; finished views stay and a rerun resumes).
In background mode (``blender -b``, or ``bpy`` as a module) ``execute`` runs to the end.
"""
from __future__ import annotations

import threading

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

from spikegen.errors import SpikegenError
from spikegen.formats import RenderJob  # the project's wheel, installed with the extension (no bpy)

_JOB = RenderJob("defaults")  # the add-on's defaults are `spikegen render`'s
DEFAULTS = {"intensities": "16,32,64", "resolution": _JOB.width, "views_train": _JOB.views[0],
            "views_val": _JOB.views[1], "views_test": _JOB.views[2], "subframes": _JOB.subframes,
            "frames": _JOB.frames, "motion_deg": _JOB.motion_deg, "samples": _JOB.samples, "denoise": _JOB.denoise,
            "seed": _JOB.seed}


DEVICES = (("PREFERENCES", "As in Preferences", "The compute device your Blender preferences select"),
           ("CPU", "CPU", "Render on the CPU"),
           ("GPU", "GPU", "The first GPU backend found (OptiX, CUDA, HIP, Metal, oneAPI); refused without one"))


def _properties():
    """The export settings, shared by the operator and the scene's PropertyGroup."""
    return {
        "directory": StringProperty(name="Folder", subtype="DIR_PATH", default=""),
        "intensities": StringProperty(name="Intensities", default=DEFAULTS["intensities"],
                                      description="Comma-separated intensities (spikes per 256 frames at X = 1)"),
        "resolution": IntProperty(name="Resolution", default=DEFAULTS["resolution"], min=8, max=4096),
        "views_train": IntProperty(name="Train views", default=DEFAULTS["views_train"], min=0),
        "views_val": IntProperty(name="Val views", default=DEFAULTS["views_val"], min=0),
        "views_test": IntProperty(name="Test views", default=DEFAULTS["views_test"], min=0),
        "subframes": IntProperty(name="Sub-frames", default=DEFAULTS["subframes"], min=1, max=256),
        "frames": IntProperty(name="Frames", default=DEFAULTS["frames"], min=1, max=100000),
        "motion_deg": FloatProperty(name="Motion (deg)", default=DEFAULTS["motion_deg"], min=0.0, max=90.0,
                                    description="Camera orbit about world Z during each view's frames; 0 = static"),
        "samples": IntProperty(name="Samples", default=DEFAULTS["samples"], min=1, max=65536),
        "denoise": BoolProperty(name="Denoise", default=DEFAULTS["denoise"],
                                description="OpenImageDenoise on every image (see docs/rendering.md)"),
        "seed": IntProperty(name="Seed", default=DEFAULTS["seed"], min=0),
        "sensor": StringProperty(name="Sensor", default="paper",
                                 description="ideal, paper, rsir, calibrated, or a sensor .json path"),
        "dataset_name": StringProperty(name="Name", default="",
                                       description="Dataset name (default: the .blend file's or the scene's name)"),
        "device": EnumProperty(name="Device", default="PREFERENCES", items=DEVICES,
                               description="Where Cycles renders (recorded in render.json; GPU and CPU bytes differ)"),
    }


SpikeExportSettings = type("SpikeExportSettings", (bpy.types.PropertyGroup,),
                           {"__annotations__": _properties()})


def parse_intensities(text: str) -> list:
    """``"16,32,64"`` -> ``[16.0, 32.0, 64.0]``; a token that is not a number stays as text, so
    the shared check names it."""
    out = []
    for t in (t.strip() for t in text.split(",")):
        if t:
            try:
                out.append(float(t))
            except ValueError:
                out.append(t)
    return out


def job_from(props, scene, camera, identify: bool = True) -> RenderJob:
    """The render job of these settings: the same record `spikegen render` builds. ``identify``:
    hash the saved .blend to name the dataset and ask Cycles for the device (skipped for the
    panel's checks, which need neither)."""
    from spikegen.render_blender import camera_angle_x, preferences_device, resolve_device

    name, source = _dataset_name(props, scene) if identify else ("scene", "scene")
    device = "cpu"
    if identify and props.device != "CPU":
        device = preferences_device() if props.device == "PREFERENCES" else resolve_device("gpu")
    res = props.resolution
    return RenderJob(name, res, res, (props.views_train, props.views_val, props.views_test), props.subframes,
                     props.frames, props.motion_deg, "cycles", props.samples,
                     RenderJob.png_samples,  # as the CLI: the job raises it to `samples` if need be
                     props.seed, camera_angle_x(camera, res, res), source, props.denoise, device)


def validate(props, context, full: bool = False) -> list[str]:
    """Messages for the user; empty when the export can start. The job, intensities and sensor go
    through the check `spikegen render` makes (:func:`spikegen.render.check_export`), before any
    rendering; ``full`` also loads the sensor (the panel, redrawn often, only checks its name)."""
    from spikegen.presets import sensor_problem
    from spikegen.render import check_export

    msgs = []
    if not props.directory:
        msgs.append("choose an output folder")
    camera = context.scene.camera
    if camera is None:
        return msgs + ["the scene has no active camera"]
    try:
        job = job_from(props, context.scene, camera, identify=full)
    except SpikegenError as exc:  # a camera the dataset cannot describe, a GPU asked for where there is none
        return msgs + [str(exc)]
    levels = parse_intensities(props.intensities)
    if full:
        return msgs + check_export(job, levels, props.sensor, props.seed)
    msgs += check_export(job, levels, "ideal", props.seed)
    problem = sensor_problem(props.sensor)
    return msgs + ([problem] if problem else [])


def _dataset_name(props, scene) -> tuple[str, str]:
    """(name, source) of the export: a recognised original NeRF-synthetic file keeps its name."""
    from spikegen.render import identify_blend

    if bpy.data.filepath and not bpy.data.is_dirty:
        name, digest = identify_blend(bpy.data.filepath)
        return props.dataset_name or name, f"blend:{digest}"
    return props.dataset_name or bpy.path.clean_name(scene.name).lower(), "scene"


class ExportSession:
    """One export, advanced a step (one image) at a time; shared by modal and background runs."""

    def __init__(self, props, context):
        from spikegen.render import RenderFolder, check_job, images_per_view, render_steps
        from spikegen.render_blender import BlenderRenderer, RenderSettings, save_settings

        scene, camera = context.scene, context.scene.camera
        self.scene, self.camera = scene, camera
        self.levels = [float(t) for t in parse_intensities(props.intensities)]
        self.sensor, self.seed, self.out = props.sensor, props.seed, bpy.path.abspath(props.directory)
        job = job_from(props, scene, camera)
        check_job(job)
        self.folder = RenderFolder.open(self.out, job)
        self.total = len(self.folder.pending()) * images_per_view(job)
        self.done = 0
        self.saved = save_settings(scene, camera)
        self.steps = render_steps(self.folder, BlenderRenderer(scene, camera, RenderSettings.for_job(job),
                                                               quiet=False))
        self.thread, self.error, self.result, self.stop = None, None, None, threading.Event()

    def step(self) -> bool:
        """Render one image; False when rendering is finished."""
        try:
            next(self.steps)
        except StopIteration:
            return False
        self.done += 1
        return True

    def cancel(self) -> None:
        """Stop: the view being rendered is removed, finished views stay (a rerun resumes)."""
        self.stop.set()
        self.steps.close()
        self.restore()

    def restore(self) -> None:
        from spikegen.render_blender import restore_settings

        if self.saved is not None:
            restore_settings(self.scene, self.camera, self.saved)
            self.saved = None

    def convert(self) -> list:
        """Spike datasets, every intensity in one pass over the renders (no bpy: safe in a thread);
        a cancel stops it between views (finished views are kept; a rerun finishes it)."""
        from spikegen.render import convert_all

        return convert_all(self.folder, self.out, self.levels, sensor=self.sensor, seed=self.seed, progress=False,
                           stop=self.stop.is_set)

    def start_convert(self) -> None:
        self.restore()
        self.thread = threading.Thread(target=self._convert_thread, daemon=True)
        self.thread.start()

    def _convert_thread(self) -> None:
        try:
            self.result = self.convert()
        except Exception as exc:  # reported by the operator in the main thread
            self.error = exc


class EXPORT_SCENE_OT_spike_dataset(bpy.types.Operator):
    """Render the scene on the NeRF camera rig and write spike-camera datasets"""

    bl_idname = "export_scene.spike_dataset"
    bl_label = "Export Spike Dataset"
    bl_options = {"REGISTER"}
    __annotations__ = _properties()

    _timer = None
    _session = None

    def invoke(self, context, event):
        stored = context.scene.spike_export
        for key in _properties():
            if not self.properties.is_property_set(key):
                setattr(self, key, getattr(stored, key))
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        msgs = validate(self, context, full=True)
        if msgs:
            self.report({"ERROR"}, "; ".join(msgs))
            return {"CANCELLED"}
        try:
            self._session = ExportSession(self, context)
        except Exception as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if bpy.app.background or context.window is None:
            return self._run_blocking()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.progress_begin(0, max(1, self._session.total))
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _run_blocking(self):
        s = self._session
        try:
            while s.step():
                pass
            s.restore()
            outs = s.convert()
        except Exception as exc:
            s.cancel()
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        self.report({"INFO"}, f"wrote {', '.join(str(o) for o in outs)}")
        return {"FINISHED"}

    def modal(self, context, event):
        s = self._session
        if event.type == "ESC":
            s.cancel()
            return self._end(context, {"WARNING"}, "spike export cancelled; finished views are kept", "CANCELLED")
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if s.thread is None:
            return self._render_tick(context)
        if s.thread.is_alive():
            return {"RUNNING_MODAL"}
        if s.error is not None:
            return self._end(context, {"ERROR"}, str(s.error), "CANCELLED")
        return self._end(context, {"INFO"}, f"wrote {', '.join(str(o) for o in s.result)}", "FINISHED")

    def _render_tick(self, context):
        s = self._session
        try:
            more = s.step()
        except Exception as exc:
            s.cancel()
            return self._end(context, {"ERROR"}, str(exc), "CANCELLED")
        context.window_manager.progress_update(s.done)
        context.workspace.status_text_set(f"Spike dataset: image {s.done} / {s.total}" if more
                                          else "Spike dataset: converting to spikes...")
        if not more:
            s.start_convert()
        return {"RUNNING_MODAL"}

    def _end(self, context, level, message, result):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        context.workspace.status_text_set(None)
        self.report(level, message)
        return {result}


class SPIKE_PT_export(bpy.types.Panel):
    bl_label = "Spike Dataset"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "output"

    def draw(self, context):
        props = context.scene.spike_export
        col = self.layout.column()
        for key in _properties():
            col.prop(props, key)
        op = col.operator(EXPORT_SCENE_OT_spike_dataset.bl_idname, icon="EXPORT")
        for key in _properties():
            setattr(op, key, getattr(props, key))
        for msg in validate(props, context):
            col.label(text=msg, icon="ERROR")


def menu_export(self, context):
    self.layout.operator(EXPORT_SCENE_OT_spike_dataset.bl_idname, text="Spike Dataset (.dat)")


CLASSES = (SpikeExportSettings, EXPORT_SCENE_OT_spike_dataset, SPIKE_PT_export)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.spike_export = PointerProperty(type=SpikeExportSettings)
    bpy.types.TOPBAR_MT_file_export.append(menu_export)


def unregister():
    bpy.types.TOPBAR_MT_file_export.remove(menu_export)
    del bpy.types.Scene.spike_export
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
