"""Headless multi-camera rasteriser: moderngl on an EGL standalone context (Mesa llvmpipe).

The GL projection is built from K exactly (OpenCV convention, pixel (0, 0)'s centre at (0, 0)):
a world point projects to the pixel centre K predicts. All cameras of a frame render into one
framebuffer (camera i in rows i·H … (i+1)·H − 1) and are read back with one call.
Shading is world-fixed: procedural texture is a function of the world position only, so the
same place looks the same from any pose (lighting and fog vary with the preset and the view).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from vvloc._checks import finite_float
from vvloc.data.frame import Camera
from vvloc.sim import world as W

MAX_LIGHTS = 8
NEAR, FAR = 0.1, 400.0


@dataclass(frozen=True)
class Lighting:
    """A lighting/weather preset. Colours are linear RGB in [0, ~2]; directions in the world."""

    name: str
    sun_dir: tuple[float, float, float] = (0.4, 0.3, 0.85)
    sun: tuple[float, float, float] = (0.75, 0.72, 0.65)
    ambient: tuple[float, float, float] = (0.5, 0.52, 0.58)
    sky: tuple[float, float, float] = (0.6, 0.72, 0.9)
    fog_color: tuple[float, float, float] = (0.7, 0.75, 0.8)
    # per metre: a surface d metres away keeps exp(-fog_density·d) of its colour
    fog_density: float = 0.002
    lamps: float = 0.0  # intensity of lamp posts / ceiling lights
    emissive: float = 0.0  # lit windows and lamp heads
    headlights: float = 0.0
    exposure: float = 1.0
    rain: float = 0.0  # streak density
    wet: float = 0.0  # specular sheen of the ground
    light_fraction: float = 1.0  # share of the lamps that work


PRESETS: dict[str, Lighting] = {
    "day": Lighting("day"),
    "dusk": Lighting(
        "dusk",
        sun_dir=(-0.8, 0.2, 0.2),
        sun=(0.7, 0.42, 0.25),
        ambient=(0.3, 0.26, 0.3),
        sky=(0.75, 0.5, 0.4),
        fog_color=(0.6, 0.45, 0.4),
        fog_density=0.004,
        lamps=0.6,
        emissive=0.5,
        headlights=0.4,
    ),
    "night": Lighting(
        "night",
        sun=(0.0, 0.0, 0.0),
        ambient=(0.05, 0.05, 0.08),
        sky=(0.02, 0.02, 0.05),
        fog_color=(0.03, 0.03, 0.05),
        fog_density=0.01,
        lamps=0.9,
        emissive=1.0,
        headlights=1.0,
        exposure=1.1,
    ),
    "rain": Lighting(
        "rain",
        sun=(0.15, 0.15, 0.16),
        ambient=(0.42, 0.44, 0.48),
        sky=(0.5, 0.52, 0.55),
        fog_color=(0.5, 0.52, 0.55),
        fog_density=0.03,
        lamps=0.4,
        emissive=0.3,
        headlights=0.6,
        rain=1.0,
        wet=1.0,
    ),
    "fog": Lighting(
        "fog",
        sun=(0.1, 0.1, 0.1),
        ambient=(0.55, 0.56, 0.58),
        sky=(0.72, 0.73, 0.75),
        fog_color=(0.72, 0.73, 0.75),
        fog_density=0.07,
        lamps=0.3,
        headlights=0.5,
    ),
    "garage": Lighting(
        "garage",
        sun=(0.0, 0.0, 0.0),
        ambient=(0.12, 0.12, 0.13),
        sky=(0.0, 0.0, 0.0),
        fog_color=(0.1, 0.1, 0.1),
        fog_density=0.01,
        lamps=0.6,
        emissive=1.0,
        headlights=0.6,
    ),
    "garage_dim": Lighting(
        "garage_dim",
        sun=(0.0, 0.0, 0.0),
        ambient=(0.07, 0.07, 0.08),
        sky=(0.0, 0.0, 0.0),
        fog_color=(0.06, 0.06, 0.06),
        fog_density=0.015,
        lamps=0.5,
        emissive=0.8,
        headlights=0.8,
        light_fraction=0.6,
    ),
}

_VERTEX = """
#version 330
in vec3 in_pos; in vec3 in_nrm; in vec3 in_col; in float in_mat;
uniform mat4 u_mvp;
out vec3 v_pos; out vec3 v_nrm; out vec3 v_col; flat out int v_mat;
void main() {
    gl_Position = u_mvp * vec4(in_pos, 1.0);
    v_pos = in_pos; v_nrm = in_nrm; v_col = in_col; v_mat = int(in_mat + 0.5);
}
"""

_FRAGMENT = """
#version 330
#define MAXL %(maxl)d
in vec3 v_pos; in vec3 v_nrm; in vec3 v_col; flat in int v_mat;
out vec4 f_color;
uniform vec3 u_cam; uniform float u_tex;
uniform vec3 u_sun_dir; uniform vec3 u_sun; uniform vec3 u_amb;
uniform vec3 u_fog_col; uniform float u_fog;
uniform int u_nl; uniform vec4 u_lpos[MAXL]; uniform vec3 u_lcol[MAXL];
uniform vec3 u_head0; uniform vec3 u_head1; uniform vec3 u_head_dir; uniform float u_head;
uniform float u_emit; uniform float u_exposure; uniform float u_rain; uniform float u_wet;
uniform float u_time; uniform vec4 u_marker;

float hash13(vec3 p) {
    p = fract(p * 0.1031);
    p += dot(p, p.zyx + 31.32);
    return fract((p.x + p.y) * p.z);
}
float hash12(vec2 p) {
    vec3 q = fract(vec3(p.xyx) * 0.1031);
    q += dot(q, q.yzx + 33.33);
    return fract((q.x + q.y) * q.z);
}
float vnoise(vec2 p) {
    vec2 i = floor(p); vec2 f = fract(p); f = f * f * (3.0 - 2.0 * f);
    return mix(mix(hash12(i), hash12(i + vec2(1.0, 0.0)), f.x),
               mix(hash12(i + vec2(0.0, 1.0)), hash12(i + vec2(1.0, 1.0)), f.x), f.y);
}
float fbm(vec2 p) { return 0.65 * vnoise(p) + 0.35 * vnoise(p * 2.13 + 17.0); }

void main() {
    vec3 p = v_pos;
    if (v_mat == %(marker)d) {
        if (u_marker.w <= 0.0) discard;
        vec3 d = p - u_marker.xyz;
        f_color = vec4(vec3(exp(-dot(d, d) / (2.0 * u_marker.w * u_marker.w))), 1.0);
        return;
    }
    vec3 n = normalize(v_nrm);
    vec3 V = normalize(u_cam - p);
    if (dot(n, V) < 0.0) n = -n;
    vec3 albedo = v_col;
    float spec = 0.0;
    vec3 emit = vec3(0.0);
    // 2-D texture coordinates fixed to the world: the ground plane, or (along the wall, height)
    float along = abs(n.x) > abs(n.y) ? p.y : p.x;
    vec2 q = abs(n.z) > 0.5 ? p.xy : vec2(along, p.z);
    if (v_mat == %(asphalt)d) {
        float t = 0.6 * (fbm(q * 1.3) - 0.5) + 0.8 * (vnoise(q * 0.17 + 5.0) - 0.5)
                + 0.25 * (hash12(floor(q * 9.0)) - 0.5);
        albedo *= 1.0 + u_tex * t;
        spec = 0.5 * u_wet;
    } else if (v_mat == %(paint)d) {
        albedo *= 1.0 - 0.45 * u_tex * smoothstep(0.5, 0.85, vnoise(q * 2.9));
    } else if (v_mat == %(car)d) {
        spec = 0.35;
    } else if (v_mat == %(glass)d) {
        spec = 0.8;
    } else if (v_mat == %(concrete)d) {
        albedo *= 1.0 + u_tex * 0.6 * (fbm(vec2(q.x * 1.3, q.y * 2.2)) - 0.5);
    } else if (v_mat == %(facade)d) {
        vec2 cell = vec2(along / 3.0, p.z / 3.2);
        vec2 f = fract(cell);
        if (p.z > 1.0 && f.x > 0.2 && f.x < 0.8 && f.y > 0.3 && f.y < 0.8) {
            float h = hash13(vec3(floor(cell), floor(dot(n, vec3(1.0, 2.0, 3.0)) * 7.0)));
            albedo = vec3(0.1, 0.12, 0.15) + 0.12 * h;
            spec = 0.6;
            emit = u_emit * step(0.55, h) * vec3(1.0, 0.85, 0.55);
        } else {
            albedo *= 1.0 + u_tex * 0.3 * (vnoise(q * 1.1) - 0.5);
        }
    } else if (v_mat == %(foliage)d) {
        albedo *= 1.0 + u_tex * 0.9 * (vnoise(q * 2.3 + p.z) - 0.5);
    } else if (v_mat == %(sign)d) {
        vec2 c = vec2(along * 5.0, p.z * 6.0);
        if (fract(c.y) > 0.3 && hash12(floor(c)) > 0.55) albedo = mix(albedo, vec3(0.95), 0.6);
    } else if (v_mat == %(emissive)d) {
        emit = v_col * (0.3 + 2.2 * u_emit);
        albedo = v_col * 0.3;
    } else if (v_mat == %(bark)d) {
        albedo *= 1.0 + u_tex * 0.4 * (vnoise(vec2(along * 8.0, p.z * 1.5)) - 0.5);
    }
    vec3 light = u_amb * (0.75 + 0.25 * n.z) + u_sun * max(dot(n, u_sun_dir), 0.0);
    vec3 hl = vec3(0.0);
    float shin = mix(48.0, 12.0, u_wet);
    hl += u_sun * pow(max(dot(reflect(-u_sun_dir, n), V), 0.0), shin);
    for (int i = 0; i < u_nl; ++i) {
        vec3 L = u_lpos[i].xyz - p;
        float d2 = dot(L, L);
        L *= inversesqrt(d2);
        float att = 1.0 / (1.0 + d2 / (u_lpos[i].w * u_lpos[i].w));
        light += u_lcol[i] * (max(dot(n, L), 0.0) * att);
        if (spec > 0.0) hl += u_lcol[i] * (att * pow(max(dot(reflect(-L, n), V), 0.0), shin));
    }
    if (u_head > 0.0) {
        for (int k = 0; k < 2; ++k) {
            vec3 L = (k == 0 ? u_head0 : u_head1) - p;
            float d2 = dot(L, L);
            L *= inversesqrt(d2);
            float cone = smoothstep(0.82, 0.95, dot(-L, u_head_dir));
            light += u_head * vec3(1.0, 0.97, 0.9) * cone * max(dot(n, L), 0.0) / (1.0 + d2 / 80.0);
        }
    }
    vec3 c = albedo * light + spec * hl + emit;
    float fog = 1.0 - exp(-u_fog * length(u_cam - p));
    c = mix(c, u_fog_col, fog);
    c *= u_exposure;
    if (u_rain > 0.0) {
        vec2 streak = vec2(floor(gl_FragCoord.x), floor(gl_FragCoord.y / 7.0 + u_time * 3.1));
        float r = hash13(vec3(streak, u_time));
        c = mix(c, vec3(0.8), 0.35 * step(1.0 - 0.04 * u_rain, r));
    }
    f_color = vec4(clamp(c, 0.0, 1.0), 1.0);
}
"""


def projection_from_K(
    K: np.ndarray, width: int, height: int, near: float = NEAR, far: float = FAR
) -> np.ndarray:
    """4×4 GL projection of OpenCV camera coordinates for intrinsics ``K``.

    Pixel centres: OpenCV puts pixel (u, v)'s centre at (u, v), GL at window (u + 0.5, v + 0.5),
    so NDC x = 2(u + 0.5)/W − 1. The y axis is *not* flipped: NDC y = 2(v + 0.5)/H − 1, so GL
    window row r is image row r and the read-back buffer needs no flip. Depth maps z = near → −1,
    z = far → +1. Includes the skew K[0, 1].
    """
    fx, s, cx = K[0, 0], K[0, 1], K[0, 2]
    fy, cy = K[1, 1], K[1, 2]
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * fx / width
    P[0, 1] = 2.0 * s / width
    P[0, 2] = 2.0 * (cx + 0.5) / width - 1.0
    P[1, 1] = 2.0 * fy / height
    P[1, 2] = 2.0 * (cy + 0.5) / height - 1.0
    P[2, 2] = (far + near) / (far - near)
    P[2, 3] = -2.0 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


def ego_to_world(pose: Sequence[float], z: float = 0.0) -> np.ndarray:
    """4×4 ego → world transform of pose (x, y, yaw) at height ``z``."""
    x, y, yaw = (float(v) for v in pose)
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (x, y, z)
    return T


def _preload_triton() -> None:
    """Load Triton's native library (bundled with CUDA builds of torch) before Mesa.

    Mesa's llvmpipe rasteriser and Triton each carry their own LLVM. When Triton's library is
    loaded *after* an EGL context has brought Mesa's LLVM into the process (torch does so
    lazily, e.g. when an optimizer is created), the process crashes with a segmentation fault;
    loaded before, both coexist. So every EGL context creation first loads Triton if present.
    """
    try:
        import triton._C.libtriton  # noqa: F401
    except Exception:  # not installed, or a build without the native library: nothing clashes
        pass


def egl_status() -> tuple[bool, str]:
    """Whether a headless EGL context can be created here, and why not."""
    try:
        import moderngl

        _preload_triton()
        ctx = moderngl.create_standalone_context(backend="egl")  # type: ignore[arg-type]
        info = ctx.info.get("GL_RENDERER", "?")
        ctx.release()
        return True, str(info)
    except Exception as e:  # any failure of the driver stack means "unavailable"
        return False, f"{type(e).__name__}: {e}"


class Renderer:
    """Renders one multi-camera frame of a mesh for an ego pose.

    Args:
        cameras: the rig; all cameras must share one image size.
        texture_strength: amplitude of the procedural texture (0: flat colours, 1: default).
    """

    def __init__(self, cameras: Sequence[Camera], *, texture_strength: float = 1.0) -> None:
        import moderngl

        if isinstance(cameras, Camera) or not all(isinstance(c, Camera) for c in cameras):
            raise TypeError("cameras: expected a sequence of Camera (a rig), e.g. [camera]")
        if not cameras:
            raise ValueError("cameras: expected at least one camera")
        sizes = {(c.width, c.height) for c in cameras}
        if len(sizes) != 1:
            raise ValueError(f"cameras: all cameras must share one image size, got {sizes}")
        texture_strength = finite_float(texture_strength, "texture_strength")
        if not texture_strength >= 0:
            raise ValueError(
                f"texture_strength: expected a finite value >= 0, got {texture_strength}"
            )
        self.cameras = tuple(cameras)
        self.width, self.height = sizes.pop()
        self.texture_strength = float(texture_strength)
        try:
            _preload_triton()
            self.ctx: Any = moderngl.create_standalone_context(backend="egl")  # type: ignore[arg-type]
        except Exception as e:
            raise RuntimeError(
                "cannot create a headless EGL OpenGL context: install Mesa's EGL "
                "(Debian: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libgl1); "
                f"cause: {type(e).__name__}: {e}"
            ) from e
        mats = {
            k.lower(): getattr(W, k)
            for k in (
                "ASPHALT",
                "PAINT",
                "CAR",
                "GLASS",
                "CONCRETE",
                "FACADE",
                "FOLIAGE",
                "SIGN",
                "EMISSIVE",
                "MARKER",
                "BARK",
            )
        }
        self.prog: Any = self.ctx.program(
            vertex_shader=_VERTEX, fragment_shader=_FRAGMENT % {"maxl": MAX_LIGHTS, **mats}
        )
        m = len(self.cameras)
        limit = int(self.ctx.info.get("GL_MAX_RENDERBUFFER_SIZE", 0) or 0)
        if limit and (self.width > limit or self.height * m > limit):
            self.ctx.release()
            raise ValueError(
                f"cameras: {m} images of {self.width}×{self.height} are rendered stacked into "
                f"one {self.width}×{self.height * m} framebuffer, over this OpenGL's limit of "
                f"{limit} pixels a side: use fewer cameras or smaller images (--cameras, "
                "--width, --height)"
            )
        self.fbo: Any = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer((self.width, self.height * m), components=4)],
            depth_attachment=self.ctx.depth_renderbuffer((self.width, self.height * m)),
        )
        self.proj = [projection_from_K(c.K, self.width, self.height) for c in self.cameras]
        self.cam_to_ego = [c.cam_to_ego for c in self.cameras]
        self.vao: Any = None
        self._buffers: list[Any] = []
        self.lights = np.zeros((0, 4), np.float32)
        self.light_colors = np.zeros((0, 3), np.float32)
        self.marker: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def set_mesh(
        self,
        vertices: np.ndarray,
        indices: np.ndarray,
        lights: np.ndarray | None = None,
        light_colors: np.ndarray | None = None,
        light_floors: np.ndarray | None = None,
    ) -> None:
        """Upload the scene: (N, 10) float32 vertices and (K,) uint32 indices as
        :meth:`vvloc.sim.world.World.mesh` gives them (world frame, metres), (L, 4) lights
        (world x, y, z and range, metres), (L, 3) light colours and (L,) the storey of each
        light (only the lights of the rendered floor shine; without floors, lights within 8 m
        above do)."""
        verts = np.ascontiguousarray(vertices, dtype=np.float32)
        if verts.ndim != 2 or verts.shape[1] != 10 or not np.isfinite(verts).all():
            raise ValueError(f"vertices: expected finite (N, 10) floats, got shape {verts.shape}")
        idx = np.asarray(indices)
        if idx.ndim != 1 or idx.size % 3 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(
                f"indices: expected (K,) integer triangle corners, K a multiple of 3, got "
                f"shape {idx.shape} of {idx.dtype}"
            )
        if idx.size and (idx.min() < 0 or idx.max() >= len(verts)):
            raise ValueError(f"indices: expected vertex numbers in [0, {len(verts)})")
        if (lights is None) != (light_colors is None):
            raise ValueError("lights, light_colors: expected both or neither")
        if lights is None:
            if light_floors is not None:
                raise ValueError("light_floors: expected None without lights")
        else:
            lights_arr, colours = np.asarray(lights), np.asarray(light_colors)
            if lights_arr.ndim != 2 or lights_arr.shape[1] != 4:
                raise ValueError(f"lights: expected (L, 4), got {lights_arr.shape}")
            n = lights_arr.shape[0]
            if colours.shape != (n, 3):
                raise ValueError(f"light_colors: expected ({n}, 3), got {colours.shape}")
            if light_floors is not None and np.shape(light_floors) != (n,):
                raise ValueError(f"light_floors: expected ({n},), got {np.shape(light_floors)}")
        for b in self._buffers:
            b.release()
        if self.vao is not None:
            self.vao.release()
        vbo = self.ctx.buffer(verts.tobytes())
        ibo = self.ctx.buffer(np.ascontiguousarray(idx, dtype=np.uint32).tobytes())
        self._buffers = [vbo, ibo]
        self.vao = self.ctx.vertex_array(
            self.prog,
            [(vbo, "3f 3f 3f 1f", "in_pos", "in_nrm", "in_col", "in_mat")],
            index_buffer=ibo,
            index_element_size=4,
        )
        self.lights = (
            np.zeros((0, 4), np.float32) if lights is None else np.asarray(lights, np.float32)
        )
        self.light_colors = (
            np.zeros((0, 3), np.float32)
            if light_colors is None
            else np.asarray(light_colors, np.float32)
        )
        self.light_floors = None if light_floors is None else np.asarray(light_floors, np.int64)

    def _set(self, name: str, value: Any) -> None:
        if name in self.prog:
            self.prog[name].value = value

    def render(
        self,
        pose: Sequence[float],
        z: float = 0.0,
        lighting: Lighting | str = "day",
        frame_index: int = 0,
        floor: int = 0,
        cam_to_ego: np.ndarray | None = None,
    ) -> np.ndarray:
        """Render the rig at ego pose (x, y, yaw) (world frame: metres, yaw in radians
        counter-clockwise) and height ``z`` (m) on storey ``floor`` (an int, a storey of the
        scene's lamps): (M, 3, H, W) uint8. ``frame_index`` seeds the rain streaks. ``cam_to_ego``
        (M, 4, 4)
        places the cameras for this frame alone (a tilting vehicle: its roll and pitch in the
        level ego frame, as ``Frame.cam_to_ego``); None uses the rig's."""
        if self.vao is None:
            raise RuntimeError("no scene: call set_mesh first")
        if isinstance(floor, (bool, np.bool_)) or not isinstance(floor, (int, np.integer)):
            raise TypeError(f"floor: expected an int storey, got {floor!r}")
        if self.light_floors is not None and floor not in set(self.light_floors.tolist()):
            # a storey the scene has no lamps on rendered a night scene without any
            raise ValueError(
                f"floor: expected a storey of the scene, one of "
                f"{sorted(set(self.light_floors.tolist()))}, got {floor}"
            )
        placements = self.cam_to_ego
        if cam_to_ego is not None:
            T = np.asarray(cam_to_ego, dtype=np.float64)
            if T.shape != (len(self.cameras), 4, 4) or not np.isfinite(T).all():
                raise ValueError(
                    f"cam_to_ego: expected finite ({len(self.cameras)}, 4, 4), got {T.shape}"
                )
            placements = list(T)
        if isinstance(lighting, str) and lighting not in PRESETS:
            raise ValueError(f"lighting: unknown preset {lighting!r}; known: {sorted(PRESETS)}")
        lt = PRESETS[lighting] if isinstance(lighting, str) else lighting
        p = np.asarray(pose, dtype=np.float64)
        if p.shape != (3,) or not np.isfinite(p).all() or not math.isfinite(z):
            raise ValueError(
                f"pose, z: expected a finite (x, y, yaw) and height, got {p.tolist()} and {z}"
            )
        T_we = ego_to_world(pose, z)
        ctx = self.ctx
        self.fbo.use()
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE)
        sky = tuple(float(v) * lt.exposure for v in lt.sky)
        fog = 1.0 - math.exp(-lt.fog_density * 200.0)
        clear = tuple(
            min(1.0, (1 - fog) * s + fog * f * lt.exposure)
            for s, f in zip(sky, lt.fog_color, strict=True)
        )
        self.fbo.clear(*clear, 1.0)
        sd = np.asarray(lt.sun_dir, dtype=np.float64)
        self._set("u_tex", self.texture_strength)
        self._set("u_sun_dir", tuple(sd / np.linalg.norm(sd)))
        self._set("u_sun", lt.sun)
        self._set("u_amb", lt.ambient)
        self._set("u_fog_col", lt.fog_color)
        self._set("u_fog", lt.fog_density)
        self._set("u_emit", lt.emissive)
        self._set("u_exposure", lt.exposure)
        self._set("u_rain", lt.rain)
        self._set("u_wet", lt.wet)
        self._set("u_time", float(frame_index % 9973))
        self._set("u_marker", self.marker)
        self._set_lights(T_we, z, lt, floor)
        head = T_we @ np.array([[3.6, 0.7, 0.7, 1.0], [3.6, -0.7, 0.7, 1.0]]).T
        hdir = T_we[:3, :3] @ np.array([0.97, 0.0, -0.12])
        self._set("u_head0", tuple(head[:3, 0]))
        self._set("u_head1", tuple(head[:3, 1]))
        self._set("u_head_dir", tuple(hdir / np.linalg.norm(hdir)))
        self._set("u_head", lt.headlights)
        for i, (P, T_ec) in enumerate(zip(self.proj, placements, strict=True)):
            T_wc = T_we @ T_ec
            mvp = P @ np.linalg.inv(T_wc)
            ctx.viewport = (0, i * self.height, self.width, self.height)
            self.prog["u_mvp"].write(mvp.T.astype("f4").tobytes())
            self._set("u_cam", tuple(T_wc[:3, 3]))
            self.vao.render()
        raw = self.fbo.read(components=3, alignment=1)
        img = np.frombuffer(raw, dtype=np.uint8).reshape(
            len(self.cameras), self.height, self.width, 3
        )
        return np.ascontiguousarray(img.transpose(0, 3, 1, 2))

    def _set_lights(self, T_we: np.ndarray, z: float, lt: Lighting, floor: int) -> None:
        if lt.lamps <= 0 or len(self.lights) == 0:
            self._set("u_nl", 0)
            return
        pos = self.lights
        if self.light_floors is not None:
            keep = np.flatnonzero(self.light_floors == floor)
        else:
            keep = np.flatnonzero((pos[:, 2] > z - 0.5) & (pos[:, 2] < z + 8.0))
        if lt.light_fraction < 1.0:
            # a fixed subset of lamps is out (a function of the lamp, not of the frame)
            h = np.modf(np.abs(pos[keep, 0] * 12.9898 + pos[keep, 1] * 78.233) * 0.1)[0]
            keep = keep[h < lt.light_fraction]
        d = np.linalg.norm(pos[keep, :2] - T_we[:2, 3], axis=1)
        order = keep[np.argsort(d, kind="stable")[:MAX_LIGHTS]]
        n = len(order)
        lpos = np.zeros((MAX_LIGHTS, 4), np.float32)
        lcol = np.zeros((MAX_LIGHTS, 3), np.float32)
        lpos[:n] = pos[order]
        lcol[:n] = self.light_colors[order] * lt.lamps
        self.prog["u_lpos"].write(lpos.tobytes())
        self.prog["u_lcol"].write(lcol.tobytes())
        self._set("u_nl", n)

    def release(self) -> None:
        """Free the GL objects and the context."""
        for b in self._buffers:
            b.release()
        if self.vao is not None:
            self.vao.release()
        self.fbo.release()
        self.prog.release()
        self.ctx.release()


def with_preset(name: str, **changes: Any) -> Lighting:
    """A copy of preset ``name`` with some fields changed."""
    if name not in PRESETS:
        raise ValueError(f"lighting: expected one of {sorted(PRESETS)}, got {name!r}")
    return replace(PRESETS[name], **changes)


os.environ.setdefault("EGL_LOG_LEVEL", "fatal")
