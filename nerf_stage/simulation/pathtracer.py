"""Numba path tracer that sorts light paths by the editable materials they hit.

Diffuse surfaces only, lit by area lights (one-sided emitting quads) and point
lights. Every surface vertex takes next-event estimation to every light; the next
direction is cosine sampled, so the path throughput is the product of the albedos
it met and nothing else: sampling never looks at an albedo, and the contribution
of each path splits exactly into (fixed factors) x (product of editable albedos).

In ``split`` mode each contribution is added to the channel of the transport term
named by the multiset of editable materials on its path (the ``next_term`` table
walks the basis of ``palette_core.basis.transport_terms``); in RGB mode editable
albedos are multiplied in like any other and everything lands in channel 0. Both
modes draw the same random numbers in the same order, so with one seed they trace
the same paths, and a path whose multiset outgrows the transport order is dropped
in both.

Arrays in, arrays out, no validation (``geometry.py`` builds them): float64
C-contiguous, index arrays int64.

References
----------
Pharr, Jakob, Humphreys. Physically Based Rendering, 3rd ed., ch. 13-14 (path
tracing with next-event estimation). 2016.
Duff et al. Building an orthonormal basis, revisited. JCGT 6(1), 2017.
Moeller, Trumbore. Fast, minimum storage ray-triangle intersection. JGT 1997.
"""

import math

import numpy as np
from numba import njit, prange

SPHERE, QUAD, TRIANGLE, DISC, CYLINDER = 0, 1, 2, 3, 4
RAY_OFFSET = 1e-5  # origin shift along the normal against self-intersection (scene units)
SHADOW_SLACK = 1e-6  # shadow rays stop this far (relative) before the light sample

_PCG_MULT = np.uint64(6364136223846793005)
_PCG_INC = np.uint64(1442695040888963407)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_GOLDEN64 = np.uint64(0x9E3779B97F4A7C15)
_TO_UNIT = 1.0 / 9007199254740992.0  # 2^-53


@njit(cache=True, inline="always")
def _mix(z):
    """SplitMix64 finaliser: a well-spread 64-bit hash of z."""
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def _uniform(state):
    """Advance an LCG state; return (new state, float in [0, 1))."""
    state = state * _PCG_MULT + _PCG_INC
    return state, float(_mix(state) >> _S11) * _TO_UNIT


@njit(cache=True)
def _shuffled_strata(state, n_pairs, spp):
    """(n_pairs, spp) int64: an independent random permutation of range(spp) per row."""
    perms = np.empty((n_pairs, spp), np.int64)
    for p in range(n_pairs):
        for i in range(spp):
            perms[p, i] = i
        for i in range(spp - 1, 0, -1):
            state, u = _uniform(state)
            j = int(u * (i + 1))
            perms[p, i], perms[p, j] = perms[p, j], perms[p, i]
    return state, perms


@njit(cache=True, inline="always")
def _sample2d(state, perms, pair, sample, grid):
    """Padded jittered sampling: sample ``sample`` of dimension pair ``pair`` in [0, 1)^2.

    Each pair's samples fall one per cell of a grid x grid lattice, the cells
    shuffled per pair so that pairs stay independent; samples beyond grid^2 (and
    pairs beyond the table) are plain uniform.
    """
    state, u = _uniform(state)
    state, v = _uniform(state)
    if pair < perms.shape[0]:
        cell = perms[pair, sample]
        if cell < grid * grid:
            return state, (cell % grid + u) / grid, (cell // grid + v) / grid
    return state, u, v


@njit(cache=True, inline="always")
def _dot(a0, a1, a2, b0, b1, b2):
    return a0 * b0 + a1 * b1 + a2 * b2


@njit(cache=True)
def _intersect(kind, d, ox, oy, oz, dx, dy, dz, tmax):
    """Distance along the ray to primitive ``d`` (a row of prim_data), or inf."""
    if kind == SPHERE:
        cx, cy, cz = ox - d[0], oy - d[1], oz - d[2]
        b = _dot(cx, cy, cz, dx, dy, dz)
        c = _dot(cx, cy, cz, cx, cy, cz) - d[3] * d[3]
        disc = b * b - c
        if disc < 0.0:
            return np.inf
        root = math.sqrt(disc)
        t = -b - root
        if t <= 0.0:
            t = -b + root
        return t if 0.0 < t < tmax else np.inf
    if kind == QUAD or kind == DISC:  # plane through d[0:3] with unit normal d[9:12] / d[3:6]
        if kind == QUAD:
            nx, ny, nz = d[9], d[10], d[11]
        else:
            nx, ny, nz = d[3], d[4], d[5]
        denom = _dot(nx, ny, nz, dx, dy, dz)
        if abs(denom) < 1e-12:
            return np.inf
        t = _dot(nx, ny, nz, d[0] - ox, d[1] - oy, d[2] - oz) / denom
        if not 0.0 < t < tmax:
            return np.inf
        px, py, pz = ox + t * dx - d[0], oy + t * dy - d[1], oz + t * dz - d[2]
        if kind == DISC:
            return t if _dot(px, py, pz, px, py, pz) <= d[6] * d[6] else np.inf
        a, b = _quad_coords(d, px, py, pz)
        return t if 0.0 <= a <= 1.0 and 0.0 <= b <= 1.0 else np.inf
    if kind == TRIANGLE:
        e1x, e1y, e1z, e2x, e2y, e2z = d[3], d[4], d[5], d[6], d[7], d[8]
        px = dy * e2z - dz * e2y
        py = dz * e2x - dx * e2z
        pz = dx * e2y - dy * e2x
        det = _dot(e1x, e1y, e1z, px, py, pz)
        if abs(det) < 1e-14:
            return np.inf
        inv = 1.0 / det
        sx, sy, sz = ox - d[0], oy - d[1], oz - d[2]
        u = _dot(sx, sy, sz, px, py, pz) * inv
        if u < 0.0 or u > 1.0:
            return np.inf
        qx = sy * e1z - sz * e1y
        qy = sz * e1x - sx * e1z
        qz = sx * e1y - sy * e1x
        v = _dot(dx, dy, dz, qx, qy, qz) * inv
        if v < 0.0 or u + v > 1.0:
            return np.inf
        t = _dot(e2x, e2y, e2z, qx, qy, qz) * inv
        return t if 0.0 < t < tmax else np.inf
    # CYLINDER: open side of radius d[6], from base d[0:3] along unit axis d[3:6] for d[7]
    cx, cy, cz = ox - d[0], oy - d[1], oz - d[2]
    o_par = _dot(cx, cy, cz, d[3], d[4], d[5])
    d_par = _dot(dx, dy, dz, d[3], d[4], d[5])
    opx, opy, opz = cx - o_par * d[3], cy - o_par * d[4], cz - o_par * d[5]
    dpx, dpy, dpz = dx - d_par * d[3], dy - d_par * d[4], dz - d_par * d[5]
    a = _dot(dpx, dpy, dpz, dpx, dpy, dpz)
    if a < 1e-14:
        return np.inf
    b = _dot(opx, opy, opz, dpx, dpy, dpz)
    c = _dot(opx, opy, opz, opx, opy, opz) - d[6] * d[6]
    disc = b * b - a * c
    if disc < 0.0:
        return np.inf
    root = math.sqrt(disc)
    for t in ((-b - root) / a, (-b + root) / a):
        h = o_par + t * d_par
        if 0.0 < t < tmax and 0.0 <= h <= d[7]:
            return t
    return np.inf


@njit(cache=True, inline="always")
def _quad_coords(d, px, py, pz):
    """Coordinates (a, b) of offset p from the corner along the quad's edges."""
    wx, wy, wz = d[12], d[13], d[14]
    ux, uy, uz, vx, vy, vz = d[3], d[4], d[5], d[6], d[7], d[8]
    a = _dot(wx, wy, wz, py * vz - pz * vy, pz * vx - px * vz, px * vy - py * vx)
    b = _dot(wx, wy, wz, uy * pz - uz * py, uz * px - ux * pz, ux * py - uy * px)
    return a, b


@njit(cache=True)
def _surface(kind, d, px, py, pz, out):
    """Write the unit geometric normal and texture coordinates at hit p: out = (n, u, v)."""
    if kind == SPHERE:
        r = d[3]
        nx, ny, nz = (px - d[0]) / r, (py - d[1]) / r, (pz - d[2]) / r
        u = 0.5 + math.atan2(nz, nx) / (2.0 * math.pi)
        v = 1.0 - math.acos(min(1.0, max(-1.0, ny))) / math.pi
    elif kind == QUAD:
        nx, ny, nz = d[9], d[10], d[11]
        u, v = _quad_coords(d, px - d[0], py - d[1], pz - d[2])
    elif kind == TRIANGLE:
        nx, ny, nz = d[9], d[10], d[11]
        # barycentrics of p from the edge frame (solve with the normal's dual basis)
        sx, sy, sz = px - d[0], py - d[1], pz - d[2]
        e11 = _dot(d[3], d[4], d[5], d[3], d[4], d[5])
        e12 = _dot(d[3], d[4], d[5], d[6], d[7], d[8])
        e22 = _dot(d[6], d[7], d[8], d[6], d[7], d[8])
        s1 = _dot(sx, sy, sz, d[3], d[4], d[5])
        s2 = _dot(sx, sy, sz, d[6], d[7], d[8])
        det = e11 * e22 - e12 * e12
        b1 = (e22 * s1 - e12 * s2) / det
        b2 = (e11 * s2 - e12 * s1) / det
        b0 = 1.0 - b1 - b2
        u = b0 * d[12] + b1 * d[14] + b2 * d[16]
        v = b0 * d[13] + b1 * d[15] + b2 * d[17]
    elif kind == DISC:
        nx, ny, nz = d[3], d[4], d[5]
        sx, sy, sz = px - d[0], py - d[1], pz - d[2]
        t1 = _dot(sx, sy, sz, d[7], d[8], d[9])
        t2 = _dot(sx, sy, sz, ny * d[9] - nz * d[8], nz * d[7] - nx * d[9], nx * d[8] - ny * d[7])
        u, v = 0.5 + t1 / (2.0 * d[6]), 0.5 + t2 / (2.0 * d[6])
    else:  # CYLINDER
        sx, sy, sz = px - d[0], py - d[1], pz - d[2]
        h = _dot(sx, sy, sz, d[3], d[4], d[5])
        nx, ny, nz = sx - h * d[3], sy - h * d[4], sz - h * d[5]
        r = math.sqrt(_dot(nx, ny, nz, nx, ny, nz))
        nx, ny, nz = nx / r, ny / r, nz / r
        ax, ay, az = d[3], d[4], d[5]
        t1 = _dot(nx, ny, nz, d[8], d[9], d[10])
        t2 = _dot(nx, ny, nz, ay * d[10] - az * d[9], az * d[8] - ax * d[10], ax * d[9] - ay * d[8])
        u = 0.5 + math.atan2(t2, t1) / (2.0 * math.pi)
        v = h / d[7]
    out[0], out[1], out[2], out[3], out[4] = nx, ny, nz, u, v


@njit(cache=True)
def _closest_hit(prim_kind, prim_data, groups, ox, oy, oz, dx, dy, dz, tmax):
    """(t, primitive index) of the nearest hit before tmax, or (inf, -1).

    ``groups`` rows are (xmin, ymin, zmin, xmax, ymax, zmax, first, end): an
    axis-aligned box around each object's primitives, tested first.
    """
    best_t, best = tmax, -1
    for g in range(groups.shape[0]):
        if not _hits_box(groups[g], ox, oy, oz, dx, dy, dz, best_t):
            continue
        for k in range(int(groups[g, 6]), int(groups[g, 7])):
            t = _intersect(prim_kind[k], prim_data[k], ox, oy, oz, dx, dy, dz, best_t)
            if t < best_t:
                best_t, best = t, k
    return best_t, best


@njit(cache=True)
def _occluded(prim_kind, prim_data, groups, ox, oy, oz, dx, dy, dz, tmax):
    """Whether anything lies on the ray before tmax (shadow rays stop at the first hit)."""
    for g in range(groups.shape[0]):
        if not _hits_box(groups[g], ox, oy, oz, dx, dy, dz, tmax):
            continue
        for k in range(int(groups[g, 6]), int(groups[g, 7])):
            if _intersect(prim_kind[k], prim_data[k], ox, oy, oz, dx, dy, dz, tmax) < tmax:
                return True
    return False


@njit(cache=True, inline="always")
def _toward(sx, sy, sz, nx, ny, nz, tx, ty, tz):
    """Unit direction from s to t, squared distance, and the cosine with normal n."""
    lx, ly, lz = tx - sx, ty - sy, tz - sz
    dist2 = lx * lx + ly * ly + lz * lz
    dist = math.sqrt(dist2)
    lx, ly, lz = lx / dist, ly / dist, lz / dist
    return lx, ly, lz, dist2, _dot(nx, ny, nz, lx, ly, lz)


@njit(cache=True, inline="always")
def _hits_box(box, ox, oy, oz, dx, dy, dz, tmax):
    """Slab test of the ray against an axis-aligned box over (0, tmax)."""
    lo, hi = 0.0, tmax
    for axis in range(3):
        o = (ox, oy, oz)[axis]
        dirn = (dx, dy, dz)[axis]
        if abs(dirn) < 1e-300:
            if o < box[axis] or o > box[axis + 3]:
                return False
            continue
        t0 = (box[axis] - o) / dirn
        t1 = (box[axis + 3] - o) / dirn
        if t0 > t1:
            t0, t1 = t1, t0
        lo, hi = max(lo, t0), min(hi, t1)
        if lo > hi:
            return False
    return True


@njit(cache=True)
def _albedo(mat, u, v, mat_albedo, mat_texture, mat_tex_scale, tex_info, tex_pixels, out):
    """Write the albedo of material ``mat`` at texture coordinates (u, v) into out."""
    tex = mat_texture[mat]
    if tex < 0:
        out[0], out[1], out[2] = mat_albedo[mat, 0], mat_albedo[mat, 1], mat_albedo[mat, 2]
        return
    offset, height, width = tex_info[tex, 0], tex_info[tex, 1], tex_info[tex, 2]
    su = u * mat_tex_scale[mat, 0]
    sv = v * mat_tex_scale[mat, 1]
    col = int(math.floor((su - math.floor(su)) * width)) % width
    row = height - 1 - int(math.floor((sv - math.floor(sv)) * height)) % height
    texel = offset + row * width + col
    out[0], out[1], out[2] = tex_pixels[texel, 0], tex_pixels[texel, 1], tex_pixels[texel, 2]


@njit(cache=True, parallel=True)
def trace_view(c2w, focal, width, height, spp, max_depth, split, seed, view_id, scene,
               next_term, out, coverage):
    """Path trace one view into per-term radiance sums.

    Parameters
    ----------
    c2w : (4, 4) camera-to-world, OpenGL axes (the camera looks down -z, y up).
    focal : focal length in pixels; width, height : image size.
    spp, max_depth : paths per pixel; surface vertices per path (1 = direct light).
    split : bool, sort contributions into transport terms (True) or render RGB (False).
    seed, view_id : the random stream of path s of pixel p depends on these, p and s only.
    scene : ``geometry.SceneArrays``, a named tuple of the scene's arrays:
        prim_kind (P,), prim_data (P, 18), prim_mat (P,), groups (G, 8) : geometry.
        mat_albedo (Mt, 3), mat_texture (Mt,), mat_tex_scale (Mt, 2), mat_palette (Mt,)
        (palette index, -1 for fixed), mat_emission (Mt, 3) : materials.
        tex_info (T, 3) (offset, height, width), tex_pixels (texels, 3) : textures.
        area_lights (La, 16) : corner, edge1, edge2, unit normal, area, emitted radiance.
        point_lights (Lp, 6) : position, intensity.
    next_term (M, K) : transport term after one more hit of material k, -1 past the order.
    out : (H * W, M, 3) zeroed, receives the mean contribution per term.
    coverage : (H * W,) zeroed, receives the fraction of camera rays that hit geometry.
    """
    n_pixels = width * height
    grid = int(math.sqrt(spp))
    while (grid + 1) * (grid + 1) <= spp:
        grid += 1
    for pixel in prange(n_pixels):
        row, col = pixel // width, pixel % width
        pixel_key = _mix(np.uint64(seed) * _GOLDEN64
                         + np.uint64(view_id) * np.uint64(n_pixels) + np.uint64(pixel))
        n_pairs = 1 + max_depth * (scene.area_lights.shape[0] + 1)
        _, perms = _shuffled_strata(pixel_key, n_pairs, spp)
        acc = out[pixel]
        surf, albedo = np.empty(5), np.empty(3)
        hits = 0
        for sample in range(spp):
            # each path has its own stream: paths cut short elsewhere do not shift it
            state = _mix(pixel_key + np.uint64(sample + 1) * _GOLDEN64)
            state, jx, jy = _sample2d(state, perms, 0, sample, grid)
            ray = _camera_ray(c2w, focal, width, height, col + jx, row + jy)
            hits += _trace_path(scene, next_term, split, max_depth, ray, state, perms, sample,
                                grid, acc, surf, albedo)
        for m in range(acc.shape[0]):
            for c in range(3):
                acc[m, c] /= spp
        coverage[pixel] = hits / spp


@njit(cache=True, inline="always")
def _camera_ray(c2w, focal, width, height, x, y):
    """(ox, oy, oz, dx, dy, dz): the camera ray through image point (x, y), unit direction."""
    cx = (x - 0.5 * width) / focal
    cy = -(y - 0.5 * height) / focal
    dx = c2w[0, 0] * cx + c2w[0, 1] * cy - c2w[0, 2]
    dy = c2w[1, 0] * cx + c2w[1, 1] * cy - c2w[1, 2]
    dz = c2w[2, 0] * cx + c2w[2, 1] * cy - c2w[2, 2]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return c2w[0, 3], c2w[1, 3], c2w[2, 3], dx / norm, dy / norm, dz / norm


@njit(cache=True, inline="always")
def _trace_path(scene, next_term, split, max_depth, ray, state, perms, sample, grid, acc,
                surf, albedo):
    """Follow one path from the camera ray ``ray``, adding its light at each surface vertex
    to ``acc`` (M, 3) by transport term (or to term 0 when not ``split``); ``surf`` (5,) and
    ``albedo`` (3,) are scratch. Returns 1 when the camera ray hits geometry, else 0."""
    prim_kind, prim_data, prim_mat, groups = (
        scene.prim_kind, scene.prim_data, scene.prim_mat, scene.groups)
    ox, oy, oz, dx, dy, dz = ray
    t, k = _closest_hit(prim_kind, prim_data, groups, ox, oy, oz, dx, dy, dz, np.inf)
    if k < 0:
        return 0
    pair = 1
    term = 0
    r, g, b = 1.0, 1.0, 1.0
    for depth in range(max_depth):
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        _surface(prim_kind[k], prim_data[k], px, py, pz, surf)
        nx, ny, nz = surf[0], surf[1], surf[2]
        facing = _dot(nx, ny, nz, dx, dy, dz) < 0.0
        if not facing:
            nx, ny, nz = -nx, -ny, -nz
        mat = prim_mat[k]
        slot = term if split else 0
        if depth == 0 and facing:
            acc[slot, 0] += r * scene.mat_emission[mat, 0]
            acc[slot, 1] += g * scene.mat_emission[mat, 1]
            acc[slot, 2] += b * scene.mat_emission[mat, 2]
        _albedo(mat, surf[3], surf[4], scene.mat_albedo, scene.mat_texture,
                scene.mat_tex_scale, scene.tex_info, scene.tex_pixels, albedo)
        entry = scene.mat_palette[mat]
        if entry >= 0:
            term = next_term[term, entry]
            if term < 0:
                break
            if not split:
                r, g, b = r * albedo[0], g * albedo[1], b * albedo[2]
        else:
            if albedo[0] == 0.0 and albedo[1] == 0.0 and albedo[2] == 0.0:
                break
            r, g, b = r * albedo[0], g * albedo[1], b * albedo[2]
        sx, sy, sz = px + RAY_OFFSET * nx, py + RAY_OFFSET * ny, pz + RAY_OFFSET * nz
        state, pair = _direct_light(scene, sx, sy, sz, nx, ny, nz, r, g, b, state, perms,
                                    pair, sample, grid, acc[term if split else 0])
        if depth + 1 == max_depth:
            break
        state, u1, u2 = _sample2d(state, perms, pair, sample, grid)
        pair += 1
        dx, dy, dz = _cosine_direction(nx, ny, nz, u1, u2)
        ox, oy, oz = sx, sy, sz
        t, k = _closest_hit(prim_kind, prim_data, groups, ox, oy, oz, dx, dy, dz, np.inf)
        if k < 0:
            break
    return 1


@njit(cache=True, inline="always")
def _direct_light(scene, sx, sy, sz, nx, ny, nz, r, g, b, state, perms, pair, sample, grid,
                  acc):
    """Next-event estimation at the shading point s (normal n): each area light sampled at
    one stratified point and each point light, added to ``acc`` (3,) times the throughput
    (r, g, b) where unoccluded. Returns the stream's state and its next pair."""
    prim_kind, prim_data, groups = scene.prim_kind, scene.prim_data, scene.groups
    for li in range(scene.area_lights.shape[0]):
        light = scene.area_lights[li]
        state, u1, u2 = _sample2d(state, perms, pair, sample, grid)
        pair += 1
        lx, ly, lz, dist2, cos_s = _toward(
            sx, sy, sz, nx, ny, nz, light[0] + u1 * light[3] + u2 * light[6],
            light[1] + u1 * light[4] + u2 * light[7],
            light[2] + u1 * light[5] + u2 * light[8])
        cos_l = -_dot(light[9], light[10], light[11], lx, ly, lz)
        if cos_s <= 0.0 or cos_l <= 0.0 or _occluded(
                prim_kind, prim_data, groups, sx, sy, sz, lx, ly, lz,
                math.sqrt(dist2) * (1.0 - SHADOW_SLACK)):
            continue
        f = cos_s * cos_l * light[12] / (math.pi * dist2)
        acc[0] += r * f * light[13]
        acc[1] += g * f * light[14]
        acc[2] += b * f * light[15]
    for li in range(scene.point_lights.shape[0]):
        light = scene.point_lights[li]
        lx, ly, lz, dist2, cos_s = _toward(sx, sy, sz, nx, ny, nz, light[0], light[1], light[2])
        if cos_s <= 0.0 or _occluded(prim_kind, prim_data, groups, sx, sy, sz, lx, ly, lz,
                                     math.sqrt(dist2) * (1.0 - SHADOW_SLACK)):
            continue
        f = cos_s / (math.pi * dist2)
        acc[0] += r * f * light[3]
        acc[1] += g * f * light[4]
        acc[2] += b * f * light[5]
    return state, pair


@njit(cache=True, inline="always")
def _cosine_direction(nx, ny, nz, u1, u2):
    """A cosine-weighted unit direction about the unit normal n for the uniform pair (u1,
    u2), in the orthonormal basis of Duff et al. (2017): the albedo is the whole throughput."""
    radius, phi = math.sqrt(u1), 2.0 * math.pi * u2
    lx, ly, lz = radius * math.cos(phi), radius * math.sin(phi), math.sqrt(1.0 - u1)
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    bb = nx * ny * a
    dx = lx * (1.0 + sign * nx * nx * a) + ly * bb + lz * nx
    dy = lx * (sign * bb) + ly * (sign + ny * ny * a) + lz * ny
    dz = lx * (-sign * nx) + ly * (-ny) + lz * nz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return dx / norm, dy / norm, dz / norm
