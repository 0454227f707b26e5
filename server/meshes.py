"""Triangle meshes for recipe parts, coloured through one shared palette texture.

Each object is drawn as one mesh per rigid link (not one visual shape per part): fewer
draw calls, so a room of ~100 objects renders fast on a software renderer. Colours come
from a fixed 32-levels-per-channel texture atlas; every vertex of a part carries the UV
of its colour's texel, so faces are flat-coloured and no mipmap blending can occur
(constant UVs have zero derivatives).

Every OBJ names the atlas through a shared MTL file (``map_Kd``), so both renderers take
the texture from the mesh file itself. ``changeVisualShape(textureUniqueId=...)`` is not
used: PyBullet's EGL plugin (3.2.x) applies it to the instancing renderer's shape whose
*index* equals the body's graphics *instance* id. The two numberings agree only while no
OBJ file is shared (the plugin caches shapes by file name), so after the first repeated
mesh (two walls of the same size) every later body lost its texture and rendered white.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
import threading

import numpy as np

from tidee.server.catalog.schema import Part

LEVELS = 32
ATLAS_W, ATLAS_H = 256, 128  # 32768 texels, one per quantised colour
ATLAS_FILE = "tidee_palette_atlas_v1.png"  # beside the OBJ files, named by MATERIAL_FILE
MATERIAL_FILE = "tidee_palette_v1.mtl"
MATERIAL = "palette"


def atlas_image() -> np.ndarray:
    """The palette texture as an RGB uint8 image (row 0 at the top)."""
    idx = np.arange(ATLAS_W * ATLAS_H)
    r, g, b = idx // (LEVELS * LEVELS), (idx // LEVELS) % LEVELS, idx % LEVELS
    scale = 255.0 / (LEVELS - 1)
    img = np.stack([r, g, b], axis=-1).reshape(ATLAS_H, ATLAS_W, 3) * scale
    return np.round(img).astype(np.uint8)


def _write_once(path: str, data: bytes) -> None:
    """Create a cache file atomically (processes and threads may race on it)."""
    if not os.path.exists(path):
        tmp = f"{path}.{os.getpid()}.{threading.get_ident()}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)


def mesh_dir() -> str:
    """The cache dir of OBJ files, holding the atlas PNG and the MTL that names it.

    The MTL's texture path is relative: PyBullet resolves it against the OBJ's folder.
    """
    folder = os.path.join(tempfile.gettempdir(), f"tidee_meshes_{os.getuid()}")
    os.makedirs(folder, exist_ok=True)
    atlas = os.path.join(folder, ATLAS_FILE)
    if not os.path.exists(atlas):
        import cv2

        _write_once(atlas, cv2.imencode(".png", atlas_image()[:, :, ::-1])[1].tobytes())
    _write_once(
        os.path.join(folder, MATERIAL_FILE), f"newmtl {MATERIAL}\nKd 1 1 1\nmap_Kd {ATLAS_FILE}\n".encode()
    )
    return folder


def hex_to_rgb(color: str) -> tuple[int, int, int]:
    c = color.lstrip("#")
    if len(c) != 6:
        raise ValueError(f"colour must be '#rrggbb', got {color!r}")
    return int(c[0:2], 16), int(c[2:4], 16), int(c[4:6], 16)


def color_uv(rgb: tuple[int, int, int]) -> tuple[float, float]:
    """UV of the atlas texel closest to an RGB colour (v measured from the bottom)."""
    q = [int(round(c / 255.0 * (LEVELS - 1))) for c in rgb]
    idx = q[0] * LEVELS * LEVELS + q[1] * LEVELS + q[2]
    row, col = divmod(idx, ATLAS_W)
    return (col + 0.5) / ATLAS_W, 1.0 - (row + 0.5) / ATLAS_H


class Mesh:
    """Triangles gathered part by part; written once as an OBJ file PyBullet can load.

    The file's name is a digest of the arrays the parts added (not of the OBJ text), so a
    mesh whose file exists already costs no text formatting: rebuilding a cached room is
    mostly PyBullet's own work."""

    def __init__(self) -> None:
        self._v: list[np.ndarray] = []
        self._n: list[np.ndarray] = []
        self._uv: list[tuple[float, float, int]] = []
        self._t: list[np.ndarray] = []
        self._count = 0
        self._hash = hashlib.sha1()

    def add(self, v: np.ndarray, n: np.ndarray, tris: np.ndarray, uv: tuple[float, float]) -> None:
        v, n = np.asarray(v, np.float64), np.asarray(n, np.float64)
        t = np.asarray(tris, np.int64) + self._count
        self._v.append(v)
        self._n.append(n)
        self._uv.append((float(uv[0]), float(uv[1]), len(v)))
        self._t.append(t)
        self._count += len(v)
        for a in (v, n, t, np.asarray(uv, np.float64)):
            self._hash.update(np.ascontiguousarray(a).tobytes())
            self._hash.update(str(a.shape).encode())

    @property
    def empty(self) -> bool:
        return not any(len(t) for t in self._t)

    @property
    def vertices(self) -> np.ndarray:
        return np.concatenate(self._v) if self._v else np.zeros((0, 3))

    def obj_text(self) -> str:
        """Wavefront OBJ with positions, UVs and normals, textured by the palette MTL
        (PyBullet's EGL renderer loads meshes only from files, not from vertex lists)."""
        lines = [f"mtllib {MATERIAL_FILE}", f"usemtl {MATERIAL}"]
        lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in self.vertices.tolist()]
        for u, v, k in self._uv:
            lines += [f"vt {u:.6f} {v:.6f}"] * k
        normals = np.concatenate(self._n).tolist() if self._n else []
        lines += [f"vn {x:.4f} {y:.4f} {z:.4f}" for x, y, z in normals]
        idx = np.concatenate([t.ravel() for t in self._t]).tolist() if self._t else []
        for k in range(0, len(idx), 3):
            a, b, c = idx[k] + 1, idx[k + 1] + 1, idx[k + 2] + 1
            lines.append(f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}")
        return "\n".join(lines) + "\n"

    def obj_file(self) -> str:
        """The mesh's OBJ file in the cache dir (written the first time); its path."""
        path = os.path.join(mesh_dir(), f"m{self._hash.hexdigest()[:20]}.obj")
        if not os.path.exists(path):
            _write_once(path, self.obj_text().encode())
        return path


def _box(half: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    verts: list[np.ndarray] = []
    norms: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    for ax in range(3):
        a, b = [i for i in range(3) if i != ax]
        for s in (-1.0, 1.0):
            base = len(verts)
            for da, db in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                q = np.zeros(3)
                q[ax], q[a], q[b] = s * half[ax], da * half[a], db * half[b]
                verts.append(q)
                nn = np.zeros(3)
                nn[ax] = s
                norms.append(nn)
            # counter-clockwise seen from outside: the (a, b) cycle is CCW about +ax
            # when (ax, a, b) is a right-handed ordering.
            right_handed = (a - ax) % 3 == 1
            ccw = (s > 0) == right_handed
            quad = [0, 1, 2, 0, 2, 3] if ccw else [0, 2, 1, 0, 3, 2]
            tris.append(np.array(quad) + base)
    return np.array(verts), np.array(norms), np.concatenate(tris).reshape(-1, 3)


def _revolve(profile: np.ndarray, segments: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface of revolution of (r, z) points about z, with caps where r > 0 at the ends."""
    th = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(th), np.sin(th)], axis=1)
    verts: list[list[float]] = []
    norms: list[list[float]] = []
    tris: list[list[int]] = []
    n_prof = len(profile)
    for i in range(n_prof - 1):
        (r0, z0), (r1, z1) = profile[i], profile[i + 1]
        dz, dr = z1 - z0, r1 - r0
        length = max(np.hypot(dz, dr), 1e-9)
        nr, nz = dz / length, -dr / length  # outward normal in the (r, z) plane
        base = len(verts)
        for j in range(segments):
            c, s = ring[j]
            verts += [[r0 * c, r0 * s, z0], [r1 * c, r1 * s, z1]]
            norms += [[nr * c, nr * s, nz]] * 2
        for j in range(segments):
            k0, k1 = base + 2 * j, base + 2 * ((j + 1) % segments)
            tris += [[k0, k1, k0 + 1], [k1, k1 + 1, k0 + 1]]
    for (r, z), up in ((profile[0], False), (profile[-1], True)):
        if r <= 1e-6:
            continue
        base = len(verts)
        verts.append([0.0, 0.0, z])
        norms.append([0.0, 0.0, 1.0 if up else -1.0])
        for j in range(segments):
            c, s = ring[j]
            verts.append([r * c, r * s, z])
            norms.append([0.0, 0.0, 1.0 if up else -1.0])
        for j in range(segments):
            a, b = base + 1 + j, base + 1 + (j + 1) % segments
            tris.append([base, a, b] if up else [base, b, a])
    return np.array(verts, float), np.array(norms, float), np.array(tris, int)


def _sphere(radius: float, rings: int = 8, segments: int = 14) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    phi = np.linspace(0, np.pi, rings + 1)  # bottom pole to top pole
    profile = np.stack([radius * np.sin(phi), -radius * np.cos(phi)], axis=1)
    v, _, t = _revolve(profile, segments)
    n = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    return v, n, t


def part_geometry(part: Part, size: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (in the object's local frame, metres), normals and triangles of a part."""
    center = np.array(part.center, float) * size
    ext = np.array(part.extent, float) * size
    if part.shape == "box":
        v, n, t = _box(ext / 2)
        return v + center, n, t
    if part.shape == "cylinder":
        r = ext[0] / 2
        profile = np.array([[r, -ext[2] / 2], [r, ext[2] / 2]])
        v, n, t = _revolve(profile, 18)
        return v + center, n, t
    if part.shape == "sphere":
        v, n, t = _sphere(ext[0] / 2)
        return v + center, n, t
    if part.shape == "lathe":
        prof = np.array(part.profile, float)
        if prof.ndim != 2 or len(prof) < 2:
            raise ValueError(f"lathe part needs a profile of at least 2 (r, z) points, got {part.profile!r}")
        radii = prof[:, 0] * ext[0] / 2
        zs = center[2] - ext[2] / 2 + prof[:, 1] * ext[2]
        v, n, t = _revolve(np.stack([radii, zs], axis=1), 20)
        v[:, :2] += center[:2]
        return v, n, t
    raise ValueError(f"unknown part shape {part.shape!r}")


def add_part(
    mesh: Mesh, part: Part, size: np.ndarray, rgb: tuple[int, int, int], offset: np.ndarray | None = None
) -> None:
    v, n, t = part_geometry(part, size)
    if offset is not None:
        v = v - offset
    mesh.add(v, n, t, color_uv(rgb))
