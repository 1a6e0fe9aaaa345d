"""The one module that talks to Blender (``bpy``, imported lazily inside functions).

- :func:`build_bpy_scene` turns a :class:`~spikegen.scenes.SceneDescription` into a Blender scene;
- :func:`open_blend` opens a user's ``.blend`` instead;
- :class:`BlenderRenderer` renders one camera pose at a time: a linear OpenEXR sub-frame
  (RGBA, premultiplied, transparent film) or the 8-bit sRGB RGBA ground-truth PNG.

Devices. Cycles renders on the CPU, or on one GPU backend (:func:`resolve_device`: OptiX, CUDA,
HIP, Metal, oneAPI, in that order of preference). A GPU render is not byte-identical to a CPU
render (different arithmetic); determinism holds per device: the same device and seed give the
same bytes, and the device is recorded in ``render.json`` so a folder is never finished on
another one.

Determinism and speed. Cycles runs with a fixed thread count (on the CPU), one tile, a fixed
seed per view (``use_animated_seed`` off, so all sub-frames of a view share one noise pattern:
noise that changed between sub-frames would turn into spurious spikes), no denoiser, no
adaptive sampling, no dithering, and persistent data (the scene is synced once; only the
camera moves between renders). For the built-in scenes Cycles renders only the box around the
object's image (the same bytes; see :class:`BlenderRenderer`). Colour management is "Standard" so
the PNG is plain sRGB.
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import CAMERA_ANGLE_X, crop_window
from .errors import InputError
from .formats import GPU_BACKENDS
from .spikeio import atomic_path

ENGINES = {"cycles": "CYCLES", "workbench": "BLENDER_WORKBENCH"}


def _bpy():
    try:
        import bpy
    except ImportError:
        raise InputError("rendering needs Blender as a Python module: pip install bpy "
                         "(or the [render] extra)") from None
    return bpy


@dataclass(frozen=True)
class RenderSettings:
    """How to render. ``threads`` 0 = all cores. The bytes do not depend on the thread count
    (tests/test_render.py checks 1 against 2 threads), so any machine renders the same files."""

    width: int = 400
    height: int = 400
    engine: str = "cycles"
    samples: int = 8
    png_samples: int = 16
    threads: int = 0
    max_bounces: int = 4
    denoise: bool = False  # OpenImageDenoise (fast quality) on every image, sub-frames and PNG
    device: str = "cpu"  # "cpu" or "gpu:<backend>" (see resolve_device)
    gpu_index: int | None = None  # render on this one GPU of the backend (None: every one in use)

    @classmethod
    def for_job(cls, job, **overrides) -> "RenderSettings":
        """The settings a :class:`~spikegen.render.RenderJob` asks for (``overrides`` replace fields)."""
        return cls(**{"width": job.width, "height": job.height, "engine": job.engine, "samples": job.samples,
                      "png_samples": job.png_render_samples, "denoise": job.denoise, "device": job.device,
                      **overrides})

    def thread_count(self) -> int:
        return self.threads or (os.cpu_count() or 1)


# ----------------------------------------------------------------------------- scene building
def reset_blender() -> None:
    """An empty Blender session (factory settings, no objects)."""
    _bpy().ops.wm.read_factory_settings(use_empty=True)


def build_bpy_scene(desc):
    """Replace the session's contents by ``desc``; return ``(scene, camera object)``."""
    bpy = _bpy()
    reset_blender()
    scene = bpy.context.scene
    materials = {name: _make_material(m) for name, m in desc.materials.items()}
    for mesh in desc.meshes:
        _make_object(scene, mesh, materials[mesh.material])
    for i, light in enumerate(desc.lights):
        _make_light(scene, light, f"light_{i}")
    set_world(scene, desc.world_color, desc.world_strength)
    camera = ensure_camera(scene)
    set_camera_angle(camera, CAMERA_ANGLE_X)
    return scene, camera


def _make_object(scene, mesh, material):
    """A Blender mesh object from ``vertices [N, 3]`` and ``faces [M, 3]``."""
    bpy = _bpy()
    data = bpy.data.meshes.new(mesh.name)
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    data.vertices.add(len(v))
    data.vertices.foreach_set("co", v.ravel())
    data.loops.add(f.size)
    data.loops.foreach_set("vertex_index", f.ravel())
    data.polygons.add(len(f))
    data.polygons.foreach_set("loop_start", np.arange(0, f.size, 3, dtype=np.int32))
    data.update(calc_edges=True)
    data.validate()
    if mesh.smooth:
        data.shade_smooth()
    data.materials.append(material)
    obj = bpy.data.objects.new(mesh.name, data)
    scene.collection.objects.link(obj)
    return obj


def _make_material(m):
    """A Principled BSDF material (optionally box-projected image texture as base colour)."""
    bpy = _bpy()
    mat = bpy.data.materials.new(m.name)
    if not mat.node_tree:  # Blender < 5 needs use_nodes; 5.x materials always have nodes
        mat.use_nodes = True
    bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*m.base_color, 1.0)
    bsdf.inputs["Roughness"].default_value = m.roughness
    bsdf.inputs["Metallic"].default_value = m.metallic
    bsdf.inputs["Transmission Weight"].default_value = m.transmission
    bsdf.inputs["IOR"].default_value = m.ior
    bsdf.inputs["Specular IOR Level"].default_value = m.specular
    mat.diffuse_color = (*m.base_color, 1.0)  # what Workbench shows
    if m.texture is not None:
        _add_texture(mat, bsdf, m)
    return mat


def _add_texture(mat, bsdf, m):
    bpy = _bpy()
    tex = np.asarray(m.texture, dtype=np.float32)
    h, w = tex.shape[:2]
    img = bpy.data.images.new(m.name + "_texture", w, h, alpha=True, float_buffer=True)
    rgba = np.concatenate([tex, np.ones((h, w, 1), np.float32)], axis=2)[::-1]  # Blender rows bottom-up
    img.pixels.foreach_set(np.ascontiguousarray(rgba).ravel())
    img.pack()
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    coord, mapping = nodes.new("ShaderNodeTexCoord"), nodes.new("ShaderNodeMapping")
    node = nodes.new("ShaderNodeTexImage")
    node.image, node.projection, node.projection_blend, node.interpolation = img, "BOX", 0.2, "Linear"
    mapping.inputs["Scale"].default_value = (m.texture_scale,) * 3
    links.new(coord.outputs["Object"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], node.inputs["Vector"])
    links.new(node.outputs["Color"], bsdf.inputs["Base Color"])


def _make_light(scene, light, name):
    bpy = _bpy()
    from mathutils import Vector

    data = bpy.data.lights.new(name, light.kind)
    data.energy = light.strength
    data.color = light.color
    if light.kind in ("AREA",):
        data.size = light.size
    elif light.kind == "POINT":
        data.shadow_soft_size = light.size
    obj = bpy.data.objects.new(name, data)
    obj.location = light.location
    obj.rotation_mode = "QUATERNION"
    obj.rotation_quaternion = Vector(light.direction).to_track_quat("-Z", "Y")
    scene.collection.objects.link(obj)
    return obj


def set_world(scene, color, strength: float) -> None:
    """A uniform world of ``color`` (linear RGB) x ``strength``."""
    bpy = _bpy()
    world = scene.world or bpy.data.worlds.new("World")
    scene.world = world
    if not world.node_tree:
        world.use_nodes = True
    bg = next(n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
    bg.inputs["Color"].default_value = (*color, 1.0)
    bg.inputs["Strength"].default_value = strength
    world.color = color


def ensure_camera(scene):
    """The scene's active camera, creating one if there is none."""
    bpy = _bpy()
    if scene.camera is None:
        cam = bpy.data.objects.new("Camera", bpy.data.cameras.new("Camera"))
        scene.collection.objects.link(cam)
        scene.camera = cam
    return scene.camera


def set_camera_angle(camera, angle_x: float) -> None:
    """Horizontal field of view ``angle_x`` (radians), fitted to the image width."""
    camera.data.sensor_fit = "HORIZONTAL"
    camera.data.sensor_width = 36.0
    camera.data.lens = 18.0 / math.tan(angle_x / 2)
    camera.data.shift_x = camera.data.shift_y = 0.0


def check_camera(camera) -> None:
    """The dataset's cameras are centred pinholes (camera_angle_x only): refuse what they cannot say."""
    data = camera.data
    if data.type != "PERSP":
        raise InputError(f"camera {camera.name!r} is {data.type.lower()}; spike datasets need a perspective "
                         f"camera (Camera > Lens > Type: Perspective)")
    if data.shift_x or data.shift_y:
        raise InputError(f"camera {camera.name!r} has a lens shift ({data.shift_x:g}, {data.shift_y:g}); the "
                         f"dataset's cameras are centred: set Shift X and Y to 0")


def camera_angle_x(camera, width: int, height: int) -> float:
    """The camera's horizontal field of view (radians) for a ``width`` x ``height`` image."""
    data = camera.data
    fit = data.sensor_fit
    if fit == "VERTICAL" or (fit == "AUTO" and height > width):
        sensor = data.sensor_height if fit == "VERTICAL" else data.sensor_width
        angle_y = 2 * math.atan(sensor / 2 / data.lens)
        return 2 * math.atan(math.tan(angle_y / 2) * width / height)
    return 2 * math.atan(data.sensor_width / 2 / data.lens)


def open_blend(path):
    """Open a user's ``.blend``; return ``(scene, camera object)`` (a camera is added if missing)."""
    bpy = _bpy()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such .blend file")
    try:
        bpy.ops.wm.open_mainfile(filepath=str(p.resolve()), load_ui=False)
    except RuntimeError as exc:
        raise InputError(f"{path}: Blender cannot open it ({str(exc).splitlines()[0]})") from None
    scene = bpy.context.scene
    return scene, ensure_camera(scene)


# ----------------------------------------------------------------------------- rendering
def configure(scene, settings: RenderSettings) -> None:
    """Engine, resolution, sampling, threads, film and colour management (see module doc)."""
    r = scene.render
    r.engine = ENGINES[settings.engine]
    r.resolution_x, r.resolution_y, r.resolution_percentage = settings.width, settings.height, 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.film_transparent = True
    r.use_persistent_data = True
    r.threads_mode, r.threads = "FIXED", settings.thread_count()
    r.dither_intensity = 0.0
    r.use_compositing = r.use_sequencer = False
    r.use_file_extension = False
    r.use_motion_blur = False
    r.use_border = False  # the whole frame; BlenderRenderer sets a border per pose for built-in scenes
    for name in dir(r):  # no date, render time, host... in the files: bytes must not depend on the run
        if name.startswith("use_stamp"):
            setattr(r, name, False)
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure, scene.view_settings.gamma = 0.0, 1.0
    scene.view_settings.use_curve_mapping = False
    if hasattr(scene.view_settings, "use_white_balance"):  # Blender 4.3+
        scene.view_settings.use_white_balance = False
    scene.display_settings.display_device = "sRGB"
    if settings.engine == "cycles":
        _configure_cycles(scene, settings)
    else:
        _configure_workbench(scene)


def _configure_cycles(scene, settings: RenderSettings) -> None:
    c = scene.cycles
    c.device = "CPU" if settings.device == "cpu" else "GPU"
    if settings.device != "cpu":
        _use_gpu(settings.device.partition(":")[2], settings.gpu_index)
    c.samples = settings.samples
    c.use_layer_samples = "IGNORE"  # a view layer's own sample count would override ours
    c.film_exposure, c.time_limit = 1.0, 0.0  # radiance as rendered; every sample, however long it takes
    c.use_sample_subset, c.sample_offset = False, 0
    c.auto_scrambling_distance, c.scrambling_distance = False, 1.0
    c.use_adaptive_sampling = False
    c.use_denoising = bool(settings.denoise)
    if settings.denoise:  # deterministic: a pure function of the (noisy) image and its passes
        c.denoiser, c.denoising_input_passes = "OPENIMAGEDENOISE", "RGB_ALBEDO_NORMAL"
        c.denoising_prefilter, c.denoising_quality, c.denoising_use_gpu = "FAST", "FAST", False
    c.use_animated_seed = False
    c.use_auto_tile = False
    c.max_bounces = settings.max_bounces
    c.diffuse_bounces, c.glossy_bounces = 2, 3
    c.transmission_bounces, c.transparent_max_bounces = settings.max_bounces + 2, 8
    c.caustics_reflective = c.caustics_refractive = False
    c.use_guiding = False
    c.pixel_filter_type, c.filter_width = "BLACKMAN_HARRIS", 1.5
    c.sample_clamp_indirect = 10.0


# ----------------------------------------------------------------------------- devices
def _cycles_preferences():
    return _bpy().context.preferences.addons["cycles"].preferences


def gpu_devices(backend: str) -> list:
    """Cycles' device entries of one GPU ``backend`` on this machine (refreshed; [] if none)."""
    prefs = _cycles_preferences()
    try:
        return [d for d in prefs.get_devices_for_type(backend) if d.type == backend]
    except (TypeError, ValueError, RuntimeError):  # a backend this Blender build does not know
        return []


def resolve_device(request: str, log=None) -> str:
    """``--device auto|cpu|gpu`` -> ``"cpu"`` or ``"gpu:<backend>"``: the first backend of
    :data:`~spikegen.formats.GPU_BACKENDS` that has a device. ``auto`` falls back to the CPU with one
    line to ``log``; ``gpu`` without a backend is an :class:`InputError`."""
    if request == "cpu":
        return "cpu"
    if request not in ("auto", "gpu"):
        raise InputError(f"--device {request!r}: expected auto, cpu or gpu")
    for backend in GPU_BACKENDS:
        if gpu_devices(backend):
            return f"gpu:{backend}"
    if request == "gpu":
        raise InputError("--device gpu: Cycles finds no GPU backend here (OptiX, CUDA, HIP, Metal, oneAPI); "
                         "use --device cpu or auto")
    if log is not None:
        log("no GPU backend found by Cycles (OptiX, CUDA, HIP, Metal, oneAPI): rendering on the CPU")
    return "cpu"


def preferences_device() -> str:
    """The device the user's own Blender preferences select: their compute backend if it has a
    device in use, else the CPU."""
    prefs = _cycles_preferences()
    backend = prefs.compute_device_type
    if backend in GPU_BACKENDS and any(d.use for d in gpu_devices(backend)):
        return f"gpu:{backend}"
    return "cpu"


def _use_gpu(backend: str, index: int | None) -> None:
    """Point Cycles at ``backend``: GPU ``index`` alone, or (None) the devices the user has in use,
    or every device of the backend when none is; never the CPU beside it (its bytes would differ)."""
    prefs = _cycles_preferences()
    devices = gpu_devices(backend)
    if not devices:
        raise InputError(f"device gpu:{backend}: Cycles finds no {backend} device here")
    if index is not None and not 0 <= index < len(devices):
        raise InputError(f"--gpu-index {index}: this machine has {len(devices)} {backend} device(s)")
    prefs.compute_device_type = backend
    chosen = [devices[index]] if index is not None else [d for d in devices if d.use] or devices
    ids = {d.id for d in chosen}
    for d in prefs.devices:
        d.use = d.id in ids


def _configure_workbench(scene) -> None:
    shading = scene.display.shading
    shading.light, shading.color_type = "STUDIO", "MATERIAL"
    scene.display.render_aa = "8"


# Settings :func:`configure` changes, restored by :func:`restore_settings` (the add-on leaves the
# user's scene as it found it).
SAVED = ("render.engine", "render.resolution_x", "render.resolution_y", "render.resolution_percentage",
         "render.film_transparent", "render.use_persistent_data", "render.threads_mode", "render.threads",
         "render.dither_intensity", "render.use_compositing", "render.use_sequencer", "render.use_file_extension",
         "render.use_motion_blur", "render.use_border", "render.use_crop_to_border", "render.border_min_x",
         "render.border_max_x", "render.border_min_y", "render.border_max_y", "render.filepath",
         "render.image_settings.file_format", "render.image_settings.color_mode", "render.image_settings.color_depth",
         "view_settings.view_transform", "view_settings.look", "view_settings.exposure", "view_settings.gamma",
         "view_settings.use_curve_mapping", "view_settings.use_white_balance", "cycles.samples",
         "cycles.use_layer_samples", "cycles.film_exposure", "cycles.time_limit", "cycles.use_sample_subset",
         "cycles.sample_offset", "cycles.auto_scrambling_distance", "cycles.scrambling_distance",
         "cycles.use_adaptive_sampling", "cycles.use_denoising", "cycles.denoiser", "cycles.denoising_input_passes",
         "cycles.denoising_prefilter", "cycles.denoising_quality", "cycles.denoising_use_gpu",
         "cycles.use_animated_seed", "cycles.seed", "cycles.max_bounces", "cycles.diffuse_bounces",
         "cycles.glossy_bounces", "cycles.transmission_bounces", "cycles.transparent_max_bounces",
         "cycles.caustics_reflective", "cycles.caustics_refractive", "cycles.device", "cycles.use_auto_tile",
         "cycles.use_guiding", "cycles.pixel_filter_type", "cycles.filter_width", "cycles.sample_clamp_indirect")


def save_settings(scene, camera) -> dict:
    """The values of :data:`SAVED` (and the stamps and camera placement) before :func:`configure`."""
    out = {}
    for path in SAVED:
        owner, attr = _owner(scene, path)
        if hasattr(owner, attr):  # (view_settings.use_white_balance is new in Blender 4.3)
            out[path] = getattr(owner, attr)
    out["stamps"] = {n: getattr(scene.render, n) for n in dir(scene.render) if n.startswith("use_stamp")}
    out["camera"] = (scene.camera, camera.matrix_world.copy(), camera.data.dof.use_dof)
    prefs = _cycles_preferences()  # a GPU render chooses the compute backend and its devices
    out["compute"] = (prefs.compute_device_type, {d.id: d.use for d in prefs.devices})
    return out


def restore_settings(scene, camera, saved: dict) -> None:
    for path in SAVED:
        if path not in saved:  # a setting this Blender does not have
            continue
        owner, attr = _owner(scene, path)
        try:
            setattr(owner, attr, saved[path])
        except (AttributeError, TypeError, ValueError):  # a value no longer valid is left as is
            pass
    for name, value in saved["stamps"].items():
        setattr(scene.render, name, value)
    scene.camera, camera.matrix_world, camera.data.dof.use_dof = saved["camera"]
    prefs = _cycles_preferences()
    backend, use = saved["compute"]
    try:
        prefs.compute_device_type = backend
    except (TypeError, ValueError):  # "NONE" where this Blender offers no backend at all: nothing was changed
        pass
    for d in prefs.devices:
        d.use = use.get(d.id, d.use)


def _owner(scene, path: str):
    *parts, attr = path.split(".")
    owner = scene
    for p in parts:
        owner = getattr(owner, p)
    return owner, attr


class BlenderRenderer:
    """Renders poses of ``camera`` in ``scene`` to files; the scene is configured once.

    ``crop_points [N, 3]``: world points whose image bounds everything the camera can see (the
    vertices of a built-in scene; the film is transparent, so every other pixel is (0, 0, 0, 0)).
    Cycles then renders only the box around their image (grown by the pixel filter's reach) and
    leaves the rest of the frame transparent: the same bytes as a full-frame render (Cycles draws
    each pixel's samples from its own coordinates; tests/test_render.py checks every scene) in
    76-88 % of the time (docs/rendering.md). ``None`` (a user's scene, which may hold anything)
    renders every pixel."""

    def __init__(self, scene, camera, settings: RenderSettings, quiet: bool = True, crop_points=None):
        self.scene, self.camera, self.settings, self.quiet = scene, camera, settings, quiet
        self.crop_points = None if crop_points is None else np.asarray(crop_points, dtype=np.float64)
        check_camera(camera)
        scene.camera = camera
        configure(scene, settings)
        camera.data.dof.use_dof = False  # a pinhole, as the dataset's cameras

    def camera_angle_x(self) -> float:
        return camera_angle_x(self.camera, self.settings.width, self.settings.height)

    def set_view_seed(self, seed: int) -> None:
        """The Cycles seed used for every render until the next call (one per view)."""
        if self.settings.engine == "cycles":
            self.scene.cycles.seed = int(seed)

    def set_pose(self, pose: np.ndarray) -> None:
        """Camera-to-world ``pose [4, 4]`` (Blender/NeRF axes)."""
        from mathutils import Matrix

        self.camera.matrix_world = Matrix(np.asarray(pose, dtype=np.float64).tolist())
        _bpy().context.view_layer.update()
        self._set_crop(pose)

    def crop_box(self, pose: np.ndarray) -> tuple[int, int, int, int] | None:
        """The pixel box ``(x0, x1, y0, y1)`` rendered at ``pose`` (``None``: the whole frame)."""
        if self.crop_points is None or self.settings.engine != "cycles":
            return None
        reach = math.ceil(self.scene.cycles.filter_width) + 2  # filter footprint, with room to spare
        return crop_window(self.crop_points, pose, self.settings.width, self.settings.height,
                           self.camera_angle_x(), margin=reach)

    def _set_crop(self, pose: np.ndarray) -> None:
        r, box = self.scene.render, self.crop_box(pose)
        r.use_border = box is not None
        if box is not None:  # Blender's border: fractions of the frame, y up
            x0, x1, y0, y1 = box
            w, h = self.settings.width, self.settings.height
            r.use_crop_to_border = False  # the full frame is written, transparent outside the box
            r.border_min_x, r.border_max_x = x0 / w, x1 / w
            r.border_min_y, r.border_max_y = (h - y1) / h, (h - y0) / h

    def camera_matrix(self) -> np.ndarray:
        """The camera's current camera-to-world ``[4, 4]`` as Blender holds it."""
        return np.array(self.camera.matrix_world, dtype=np.float64)

    def render_exr(self, pose: np.ndarray, path) -> None:
        """Linear RGBA half-float OpenEXR (ZIP) of ``pose`` (premultiplied alpha, transparent film).

        Half floats carry 11 significant bits (0.05 % steps), far below render and spike noise,
        at less than half the disk space of float32."""
        self.set_pose(pose)
        fmt = self.scene.render.image_settings
        fmt.file_format, fmt.color_mode, fmt.color_depth, fmt.exr_codec = "OPEN_EXR", "RGBA", "16", "ZIP"
        self._render_to(path, self.settings.samples, _rewrite_exr)

    def render_png(self, pose: np.ndarray, path) -> None:
        """8-bit sRGB RGBA PNG of ``pose`` (straight alpha, transparent film), as NeRF-synthetic."""
        self.set_pose(pose)
        fmt = self.scene.render.image_settings
        fmt.file_format, fmt.color_mode, fmt.color_depth, fmt.compression = "PNG", "RGBA", "8", 15
        self._render_to(path, self.settings.png_samples, _rewrite_png)

    def _render_to(self, path, samples: int, rewrite) -> None:
        bpy = _bpy()
        if self.settings.engine == "cycles":
            self.scene.cycles.samples = samples
        with atomic_path(path) as tmp:
            with quiet_stdout(self.quiet):
                self.scene.render.filepath = str(tmp)
                bpy.ops.render.render(write_still=True, scene=self.scene.name)
            rewrite(tmp)


_DIGITS = bytes.maketrans(b"123456789", b"000000000")


def _timeless(name: bytes) -> bool:
    """Metadata whose value changes from run to run (Cycles stamps render and sync times)."""
    return b"time" in name.lower()


def _rewrite_exr(path) -> None:
    """Zero the digits of Blender's timing attributes in an EXR header, in place.

    Header attributes are ``name\0 type\0 size:int32 value``; values keep their length, so
    the offset table after the header stays valid and the pixels are untouched. Without this,
    identical renders would differ in bytes.
    """
    data = bytearray(Path(path).read_bytes())
    pos = 8  # magic number and version
    while data[pos] != 0:
        name_end = data.index(0, pos)
        type_end = data.index(0, name_end + 1)
        size = int.from_bytes(data[type_end + 1:type_end + 5], "little")
        value = type_end + 5
        if _timeless(bytes(data[pos:name_end])):
            data[value:value + size] = bytes(data[value:value + size]).translate(_DIGITS)
        pos = value + size
    Path(path).write_bytes(bytes(data))


def _rewrite_png(path) -> None:
    """Zero the digits of Blender's timing text chunks in a PNG, in place (CRCs recomputed)."""
    data = bytearray(Path(path).read_bytes())
    pos = 8  # signature
    while pos < len(data):
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind, body = bytes(data[pos + 4:pos + 8]), pos + 8
        if kind == b"tEXt":
            key = bytes(data[body:body + length]).split(b"\0", 1)[0]
            if _timeless(key):
                data[body:body + length] = bytes(data[body:body + length]).translate(_DIGITS)
                crc = zlib.crc32(bytes(data[pos + 4:body + length])) & 0xFFFFFFFF
                data[body + length:body + length + 4] = crc.to_bytes(4, "big")
        pos = body + length + 4
    Path(path).write_bytes(bytes(data))


@contextlib.contextmanager
def quiet_stdout(enabled: bool = True):
    """Silence Blender's per-render log lines (written by C code straight to file descriptor 1)."""
    if not enabled:
        yield
        return
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def renderer_for(job, blend=None, quiet: bool = True, gpu_index: int | None = None) -> "BlenderRenderer":
    """A renderer for ``job``: the built-in scene ``job.scene``, or the user's ``blend`` file."""
    settings = RenderSettings.for_job(job, gpu_index=gpu_index)
    if blend is None:
        return builtin_renderer(job.scene, settings, quiet=quiet)
    scene, camera = open_blend(blend)
    return BlenderRenderer(scene, camera, settings, quiet=quiet)


def builtin_renderer(name: str, settings: RenderSettings, quiet: bool = True) -> "BlenderRenderer":
    """A renderer for the built-in scene ``name``, rendering only the box around its image."""
    from .scenes import build_scene

    desc = build_scene(name)
    scene, camera = build_bpy_scene(desc)
    return BlenderRenderer(scene, camera, settings, quiet=quiet, crop_points=desc.vertices())
