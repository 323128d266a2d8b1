"""Numba kernels of the fast batched world: lidar depth buffer, contacts, single-track model, traffic.

Arrays are batched as (n_worlds, n_cars, ...); car 0 of every world is the agent. Everything here
is plain arithmetic on arrays handed in by :mod:`racecav.sim.fast_world`, which reads
the geometry (World.walls), car (CarParams) and lidar (LidarSpec) definitions: no parameter lives
in this file.

Lidar algorithm (chosen by measurement, see ../shared/reference/measurements.md): every wall
segment and every visible edge of another car's box is transformed into the sensor frame, clipped
to the half-plane ahead (x > eps; a segment that starts behind the car and ends in front would
otherwise get a wrong angular span), and its angular span is rasterised into the ray bins it
covers; each covered ray gets the exact ray/line distance, kept if nearer (a 1-D depth buffer).
The per-ray distance is one division: ``t = cross(a, d) / cross(ray, d)`` with the numerator
constant per segment.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

EPS_AHEAD = 1e-3  # m: segments are clipped to x >= EPS_AHEAD in the sensor frame


@njit(cache=True, fastmath=True, inline="always")
def _fast_atan(t):
    """atan(t) within ~1e-3 rad (only used to guess a bin; the bins are then fixed exactly)."""
    a = abs(t)
    inv = a > 1.0
    if inv:
        a = 1.0 / a
    r = a * (0.7853981633974483 + 0.273 * (1.0 - a))
    if inv:
        r = 1.5707963267948966 - r
    return r if t >= 0.0 else -r


@njit(cache=True, fastmath=True, inline="always")
def _raster(buf, ax, ay, bx, by, ray_c, ray_s, ray_t, amin, inv_inc, n):
    """Rasterise segment a-b (sensor frame) into the depth buffer ``buf``.

    The covered rays are those whose slope ``tan(angle)`` lies between the slopes ``y / x`` of
    the (clipped) end points: exact comparisons against the table ``ray_t``, after a cheap
    guess of the index, so that two faces sharing an end point leave no ray between them."""
    if ax < EPS_AHEAD and bx < EPS_AHEAD:
        return
    # Cull: both ends right of the first ray's line or both left of the last ray's line
    # (a half-plane is convex, so the whole segment is outside the fan; valid for fov <= 180 deg).
    c0 = ray_c[0]
    s0 = ray_s[0]
    c1 = ray_c[n - 1]
    s1 = ray_s[n - 1]
    if c0 * ay - s0 * ax < 0.0 and c0 * by - s0 * bx < 0.0:
        return
    if c1 * ay - s1 * ax > 0.0 and c1 * by - s1 * bx > 0.0:
        return
    dx = bx - ax
    dy = by - ay
    num = ax * dy - ay * dx
    # One-sided: a face is seen only from the side of its outward normal, the right-hand normal
    # (dy, -dx) of its direction (CCW box edges, wall faces built by wall_faces()).
    if num >= 0.0:
        return
    cx0 = ax
    cy0 = ay
    cx1 = bx
    cy1 = by
    if cx0 < EPS_AHEAD:
        u = (EPS_AHEAD - ax) / dx
        cx0 = EPS_AHEAD
        cy0 = ay + u * dy
    elif cx1 < EPS_AHEAD:
        u = (EPS_AHEAD - ax) / dx
        cx1 = EPS_AHEAD
        cy1 = ay + u * dy
    t0 = cy0 / cx0
    t1 = cy1 / cx1
    if t0 > t1:
        t = t0
        t0 = t1
        t1 = t
    if t1 < ray_t[0] or t0 > ray_t[n - 1]:
        return
    i0 = int(math.ceil((_fast_atan(t0) - amin) * inv_inc))
    i0 = min(max(i0, 0), n - 1)
    while i0 > 0 and ray_t[i0 - 1] >= t0:
        i0 -= 1
    while i0 < n - 1 and ray_t[i0] < t0:
        i0 += 1
    i1 = int(math.floor((_fast_atan(t1) - amin) * inv_inc))
    i1 = min(max(i1, 0), n - 1)
    while i1 < n - 1 and ray_t[i1 + 1] <= t1:
        i1 += 1
    while i1 > 0 and ray_t[i1] > t1:
        i1 -= 1
    if ray_t[i0] < t0 or ray_t[i1] > t1:
        return
    for i in range(i0, i1 + 1):
        den = ray_c[i] * dy - ray_s[i] * dx
        if den != 0.0:
            t = num / den
            if t > 0.0 and t < buf[i]:
                buf[i] = t


@njit(cache=True, fastmath=True)
def box_corners(x, y, yaw, hx, hy, out):
    """Corners (CCW: rear-right, front-right, front-left, rear-left) of every car's box.

    :param x, y, yaw: (N, C) poses of base_link (box centre).
    :param hx, hy: half length / half width (m).
    :param out: (N, C, 4, 2) written in place.
    """
    N, C = x.shape
    for n in range(N):
        for c in range(C):
            ca = math.cos(yaw[n, c])
            sa = math.sin(yaw[n, c])
            for k in range(4):
                lx = hx if (k == 1 or k == 2) else -hx
                ly = hy if k >= 2 else -hy
                out[n, c, k, 0] = x[n, c] + ca * lx - sa * ly
                out[n, c, k, 1] = y[n, c] + sa * lx + ca * ly


@njit(cache=True, fastmath=True)
def lidar(x, y, yaw, active, observe, faces, chunks, corners, mount, ray_c, ray_s, ray_t, amin,
          inc, range_max, out):
    """170-ray (or any) lidar of every observing car against walls and the other cars' boxes.

    :param x, y, yaw: (N, C) car poses.
    :param active: (N, C) bool, cars present in the world (others are neither seen nor see).
    :param observe: (N, C) bool, cars whose scan is computed.
    :param faces: (F, 4) float64 one-sided wall faces x0, y0, x1, y1 (see :func:`wall_faces`).
    :param chunks: (K, 5) groups of consecutive faces: bounding circle x, y, radius, first face,
        end face (see :func:`face_chunks`); one chunk holding every face disables the culling.
    :param corners: (N, C, 4, 2) box corners from :func:`box_corners`.
    :param mount: (3,) sensor x, y, yaw in the car frame.
    :param ray_c, ray_s, ray_t: cos/sin/tan of the ray angles (laser frame, |angle| < 90 deg).
    :param out: (N, C, R) float32, written where ``observe``: distance, +inf where no return
        within range_max (the Scan message's convention).
    """
    N, C = x.shape
    buf = np.empty(ray_c.shape[0])
    work = np.empty((chunks.shape[0], 2))
    for n in range(N):
        for c in range(C):
            if observe[n, c]:
                _scan_one(n, c, x, y, yaw, active, faces, chunks, corners, mount, ray_c, ray_s,
                          ray_t, amin, inc, range_max, buf, work, out)


@njit(cache=True, fastmath=True, parallel=True)
def lidar_parallel(x, y, yaw, active, observe, faces, chunks, corners, mount, ray_c, ray_s, ray_t,
                   amin, inc, range_max, out):
    """:func:`lidar` with the scans spread over numba's threads."""
    N, C = x.shape
    for k in prange(N * C):
        n = k // C
        c = k % C
        if observe[n, c]:
            buf = np.empty(ray_c.shape[0])
            work = np.empty((chunks.shape[0], 2))
            _scan_one(n, c, x, y, yaw, active, faces, chunks, corners, mount, ray_c, ray_s,
                      ray_t, amin, inc, range_max, buf, work, out)


@njit(cache=True, fastmath=True)
def _scan_one(n, c, x, y, yaw, active, faces, chunks, corners, mount, ray_c, ray_s, ray_t, amin,
              inc, range_max, buf, work, out):
    """The scan of car c of world n into out[n, c] (``buf``: work array of n_rays, ``work``:
    (n_chunks, 2)).

    Order: the other cars' boxes, then the wall chunks nearest first. A chunk is skipped when
    its bounding circle is out of range, outside the fan of rays, or occluded: every ray that can
    reach the circle already holds a distance no larger than the circle's nearest point (then no
    face of the chunk could change the buffer: the result is exactly that of rasterising all).
    """
    C = x.shape[1]
    K = chunks.shape[0]
    R = ray_c.shape[0]
    inv_inc = 1.0 / inc
    cy = math.cos(yaw[n, c])
    sy = math.sin(yaw[n, c])
    sx = x[n, c] + cy * mount[0] - sy * mount[1]
    sy_ = y[n, c] + sy * mount[0] + cy * mount[1]
    syaw = yaw[n, c] + mount[2]
    ca = math.cos(syaw)
    sa = math.sin(syaw)
    for i in range(R):
        buf[i] = range_max
    # first / last ray directions in the world frame (fan cull before rotating)
    wc0 = ca * ray_c[0] - sa * ray_s[0]
    ws0 = sa * ray_c[0] + ca * ray_s[0]
    wc1 = ca * ray_c[R - 1] - sa * ray_s[R - 1]
    ws1 = sa * ray_c[R - 1] + ca * ray_s[R - 1]
    # the other cars first: they are near and occlude walls
    for j in range(C):
        if j == c or not active[n, j]:
            continue
        # the box's circumscribed circle (centre = middle of a diagonal): range and fan culls
        ddx = 0.5 * (corners[n, j, 0, 0] + corners[n, j, 2, 0]) - sx
        ddy = 0.5 * (corners[n, j, 0, 1] + corners[n, j, 2, 1]) - sy_
        crad = 0.5 * math.hypot(corners[n, j, 2, 0] - corners[n, j, 0, 0],
                                corners[n, j, 2, 1] - corners[n, j, 0, 1])
        if ddx * ddx + ddy * ddy > (range_max + crad) ** 2:
            continue
        if wc0 * ddy - ws0 * ddx < -crad or wc1 * ddy - ws1 * ddx > crad:
            continue
        for k in range(4):
            k2 = (k + 1) % 4
            ax = corners[n, j, k, 0] - sx
            ay = corners[n, j, k, 1] - sy_
            bx = corners[n, j, k2, 0] - sx
            by = corners[n, j, k2, 1] - sy_
            _raster(buf, ca * ax + sa * ay, -sa * ax + ca * ay, ca * bx + sa * by,
                    -sa * bx + ca * by, ray_c, ray_s, ray_t, amin, inv_inc, R)
    # wall chunks in range and in the fan of rays, nearest first (insertion sort)
    ns = 0
    for k in range(K):
        rad = chunks[k, 2]
        cx = chunks[k, 0] - sx
        cy_ = chunks[k, 1] - sy_
        if wc0 * cy_ - ws0 * cx < -rad or wc1 * cy_ - ws1 * cx > rad:
            continue  # the circle is beyond the first or the last ray's line
        d = math.sqrt(cx * cx + cy_ * cy_)
        if d - rad > range_max:
            continue
        q = ns
        while q > 0 and work[q - 1, 0] > d:
            work[q, 0] = work[q - 1, 0]
            work[q, 1] = work[q - 1, 1]
            q -= 1
        work[q, 0] = d
        work[q, 1] = k
        ns += 1
    for kk in range(ns):
        d = work[kk, 0]
        k = int(work[kk, 1])
        rad = chunks[k, 2]
        cx = chunks[k, 0] - sx
        cy_ = chunks[k, 1] - sy_
        if d > rad:
            # rays that can reach the circle; skip the chunk if they all already stop nearer
            th = math.atan2(-sa * cx + ca * cy_, ca * cx + sa * cy_)
            half = math.asin(rad / d)
            i0 = int(math.floor((th - half - amin) * inv_inc)) - 1
            i1 = int(math.ceil((th + half - amin) * inv_inc)) + 1
            if i1 < 0 or i0 > R - 1:
                continue
            i0 = max(i0, 0)
            i1 = min(i1, R - 1)
            dmin = d - rad
            hidden = True
            for i in range(i0, i1 + 1):
                if buf[i] > dmin:
                    hidden = False
                    break
            if hidden:
                continue
        for m in range(int(chunks[k, 3]), int(chunks[k, 4])):
            ax = faces[m, 0] - sx
            ay = faces[m, 1] - sy_
            bx = faces[m, 2] - sx
            by = faces[m, 3] - sy_
            # back face (the cross product is rotation invariant): not seen
            if ax * (by - ay) - ay * (bx - ax) >= 0.0:
                continue
            # both ends beyond range on one side: cannot be seen
            if (ax > range_max and bx > range_max) or (ax < -range_max and bx < -range_max):
                continue
            if (ay > range_max and by > range_max) or (ay < -range_max and by < -range_max):
                continue
            # outside the fan of rays (both ends beyond the first or the last ray's line)
            if wc0 * ay - ws0 * ax < 0.0 and wc0 * by - ws0 * bx < 0.0:
                continue
            if wc1 * ay - ws1 * ax > 0.0 and wc1 * by - ws1 * bx > 0.0:
                continue
            pax = ca * ax + sa * ay
            pay = -sa * ax + ca * ay
            pbx = ca * bx + sa * by
            pby = -sa * bx + ca * by
            _raster(buf, pax, pay, pbx, pby, ray_c, ray_s, ray_t, amin, inv_inc, R)
    for i in range(R):
        out[n, c, i] = buf[i] if buf[i] < range_max else np.inf


def wall_faces(walls: np.ndarray, half_thickness: float, extend: float = 0.0) -> np.ndarray:
    """The four faces of every wall box (centred on the segment, ``2 * half_thickness`` thick,
    the segment's length plus ``extend`` at each end), as the PyBullet backend builds them;
    CCW, so that each face's outward normal is its right-hand normal (one-sided rasterising).

    :param walls: (M, 4) wall centre lines.
    :return: (4M, 4) float64 faces x0, y0, x1, y1, the four of wall i at 4i..4i+3.
    """
    w = np.asarray(walls, dtype=np.float64)
    a, b = w[:, :2], w[:, 2:]
    d = b - a
    u = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    nl = np.stack([-u[:, 1], u[:, 0]], axis=1)
    r = half_thickness
    p0 = a - extend * u - r * nl   # rear right (CCW order seen from above)
    p1 = b + extend * u - r * nl
    p2 = b + extend * u + r * nl
    p3 = a - extend * u + r * nl
    faces = [np.concatenate(e, axis=1) for e in ((p0, p1), (p1, p2), (p2, p3), (p3, p0))]
    # wall by wall (faces 4i..4i+3 belong to wall i): consecutive walls make compact chunks
    return np.ascontiguousarray(np.stack(faces, axis=1).reshape(-1, 4))


def face_chunks(faces: np.ndarray, per_chunk: int) -> np.ndarray:
    """Groups of ``per_chunk`` consecutive faces with their bounding circles (for culling).

    :return: (K, 5) float64 centre x, y, radius, first face, end face (exclusive).
    """
    out = []
    for start in range(0, len(faces), per_chunk):
        pts = faces[start:start + per_chunk].reshape(-1, 2)
        centre = 0.5 * (pts.min(0) + pts.max(0))
        rad = np.sqrt(((pts - centre) ** 2).sum(1)).max() + 1e-6
        out.append([centre[0], centre[1], rad, start, min(start + per_chunk, len(faces))])
    return np.asarray(out, dtype=np.float64).reshape(-1, 5)


@njit(cache=True, fastmath=True, inline="always")
def _segment_hits_box(ax, ay, bx, by, hx, hy):
    """Liang-Barsky: does segment a-b (box frame) intersect the box [-hx,hx] x [-hy,hy]?"""
    t0 = 0.0
    t1 = 1.0
    dx = bx - ax
    dy = by - ay
    for k in range(4):
        if k == 0:
            p = -dx
            q = ax + hx
        elif k == 1:
            p = dx
            q = hx - ax
        elif k == 2:
            p = -dy
            q = ay + hy
        else:
            p = dy
            q = hy - ay
        if p == 0.0:
            if q < 0.0:
                return False
        else:
            r = q / p
            if p < 0.0:
                if r > t1:
                    return False
                if r > t0:
                    t0 = r
            else:
                if r < t0:
                    return False
                if r < t1:
                    t1 = r
    return True


@njit(cache=True, fastmath=True, inline="always")
def _boxes_overlap(corners, n, a, b):
    """Separating-axis test of two cars' boxes (4 axes: the edge directions of each box)."""
    for box in range(2):
        o = a if box == 0 else b
        for e in range(2):
            ex = corners[n, o, e + 1, 0] - corners[n, o, e, 0]
            ey = corners[n, o, e + 1, 1] - corners[n, o, e, 1]
            amin_ = 1e30
            amax_ = -1e30
            bmin_ = 1e30
            bmax_ = -1e30
            for k in range(4):
                pa = corners[n, a, k, 0] * ex + corners[n, a, k, 1] * ey
                pb = corners[n, b, k, 0] * ex + corners[n, b, k, 1] * ey
                amin_ = min(amin_, pa)
                amax_ = max(amax_, pa)
                bmin_ = min(bmin_, pb)
                bmax_ = max(bmax_, pb)
            if amax_ < bmin_ or bmax_ < amin_:
                return False
    return True


@njit(cache=True, fastmath=True)
def contacts(x, y, yaw, active, walls, wall_box, corners, hx, hy, wall_r, check, out_wall, out_car):
    """Contact of each checked car with the walls and with the other cars.

    :param wall_box: (M, 4) per-segment AABB xmin, ymin, xmax, ymax (cull).
    :param wall_r: half wall thickness (m): walls are segments inflated by it (the box is inflated
        instead: square corners, an over-estimate of at most 0.41 * wall_r at the box corners).
    :param check: (N, C) bool, cars to test.
    :param out_wall: (N, C) bool, OR-ed in (so substeps accumulate).
    :param out_car: (N, C) int, index of a car in contact (or left unchanged = -1 by the caller).
    """
    N, C = x.shape
    M = walls.shape[0]
    rad = math.sqrt(hx * hx + hy * hy) + wall_r
    for n in range(N):
        for c in range(C):
            if not check[n, c] or not active[n, c]:
                continue
            cx = x[n, c]
            cy = y[n, c]
            ca = math.cos(yaw[n, c])
            sa = math.sin(yaw[n, c])
            if not out_wall[n, c]:
                for m in range(M):
                    if (wall_box[m, 0] > cx + rad or wall_box[m, 2] < cx - rad
                            or wall_box[m, 1] > cy + rad or wall_box[m, 3] < cy - rad):
                        continue
                    ax = walls[m, 0] - cx
                    ay = walls[m, 1] - cy
                    bx = walls[m, 2] - cx
                    by = walls[m, 3] - cy
                    if _segment_hits_box(ca * ax + sa * ay, -sa * ax + ca * ay,
                                         ca * bx + sa * by, -sa * bx + ca * by,
                                         hx + wall_r, hy + wall_r):
                        out_wall[n, c] = True
                        break
            for j in range(C):
                if j == c or not active[n, j]:
                    continue
                ddx = x[n, j] - cx
                ddy = y[n, j] - cy
                if ddx * ddx + ddy * ddy > 4.0 * (hx * hx + hy * hy):
                    continue
                if _boxes_overlap(corners, n, c, j):
                    out_car[n, c] = j
                    break


@njit(cache=True, fastmath=True)
def integrate(x, y, yaw, v, beta, r, delta, delta_cmd, w, speed_scale, active, skid, wheel_radius,
              wheelbase, mass, g, lf, lr, iz, mu, c_sf, c_sr, steer_tau, speed_tau, scrub,
              scrub_lat, v_kin, dt, c_speed_inv=0.0, heading_c4=0.0, heading_s4=0.0, a_lat_max=math.inf):
    """One physics substep of the single-track model for every car.

    The wheel speed ``w`` and the rate-limited steering command ``delta_cmd`` of this substep come
    from the shared actuation functions (common/vehicle.py); this adds the fitted lags and
    integrates the CommonRoad/f1tenth single-track model (no load transfer) in its state
    (slip angle ``beta`` and yaw rate ``r`` at the CoG, ``lr`` ahead of the rear axle), with
    implicit Euler for (beta, r) (stiff at low speed) and the kinematic model below ``v_kin``.
    The speed at the CoG follows the wheel speed (lag ``speed_tau``), reduced in turns by
    ``1 - scrub * tan(delta)^2 - scrub_lat * |a_lat|`` (tyre scrub of the locked 4WD, and drag
    of the slipping tyres growing with the lateral acceleration ``a_lat = r v`` of the previous
    substep). The pose is base_link's.

    Two terms reproduce PyBullet's tyre contact (0 = the classic model): the cornering stiffnesses
    scale with ``1 + c_speed_inv (1 m/s / v - 1)`` (1: inversely with speed), and the steering
    angle the tyres see is ``delta * (1 + heading_c4 cos 4psi + heading_s4 sin 4psi)`` with ``psi``
    the yaw (mirrored, ``-yaw``, in right turns): PyBullet's grip depends on the heading relative
    to the world axes (period 90 deg), so its turning circle breathes with the heading.

    ``skid`` (N, C) bool: braking cars, whose locked wheels slide straight (PyBullet: no lateral
    grip, the steering angle has no effect until the brake is released).

    ``a_lat_max``: the yaw rate is capped so that ``r v`` stays within it (m/s^2): a floor of
    friction mu < 1 holds at most mu g sideways (common/perturb.py); inf: the fitted model alone.
    """
    N, C = x.shape
    L = lf + lr
    ks = dt / steer_tau if steer_tau > dt else 1.0
    kv = dt / speed_tau if speed_tau > dt else 1.0
    ox = 0.5 * wheelbase - lr  # base_link ahead of the CoG (m)
    aniso = heading_c4 != 0.0 or heading_s4 != 0.0
    for n in range(N):
        for c in range(C):
            if not active[n, c]:
                continue
            delta[n, c] += (delta_cmd[n, c] - delta[n, c]) * ks
            d = 0.0 if skid[n, c] else delta[n, c]
            if aniso:  # cos/sin of 4 yaw by double angles
                c1 = math.cos(yaw[n, c])
                s1 = math.sin(yaw[n, c])
                c2 = c1 * c1 - s1 * s1
                s2 = 2.0 * s1 * c1
                s4 = math.copysign(2.0, d) * s2 * c2  # mirrored in right turns
                d *= 1.0 + heading_c4 * (c2 * c2 - s2 * s2) + heading_s4 * s4
            td = math.tan(d)
            loss = scrub * td * td + scrub_lat * abs(r[n, c] * v[n, c])
            v_target = speed_scale[n, c] * w[n, c] * wheel_radius * max(0.0, 1.0 - loss)
            v0 = v[n, c]
            v1 = v0 + (v_target - v0) * kv
            vm = 0.5 * (v0 + v1)
            if vm < v_kin:
                b = math.atan(lr / L * td)
                rr = vm * math.cos(b) * td / L
            else:
                csf = c_sf
                csr = c_sr
                if c_speed_inv != 0.0:
                    sp = max(1.0 + c_speed_inv * (1.0 / vm - 1.0), 0.05)
                    csf *= sp
                    csr *= sp
                a11 = -mu * g * (csr * lf + csf * lr) / (vm * L)
                a12 = mu * g * lf * lr * (csr - csf) / (vm * vm * L) - 1.0
                b1 = mu * g * csf * lr / (vm * L)
                a21 = mu * mass * g * lf * lr * (csr - csf) / (iz * L)
                a22 = -mu * mass * g * lf * lr * (lf * csf + lr * csr) / (iz * L * vm)
                b2 = mu * mass * g * lf * lr * csf / (iz * L)
                # (I - dt A) x1 = x0 + dt b d
                m11 = 1.0 - dt * a11
                m12 = -dt * a12
                m21 = -dt * a21
                m22 = 1.0 - dt * a22
                r1 = beta[n, c] + dt * b1 * d
                r2 = r[n, c] + dt * b2 * d
                det = m11 * m22 - m12 * m21
                b = (m22 * r1 - m12 * r2) / det
                rr = (m11 * r2 - m21 * r1) / det
                if abs(rr * vm) > a_lat_max:  # the tyres slide: the car runs wide
                    rr = math.copysign(a_lat_max / vm, rr)
            beta[n, c] = b
            r[n, c] = rr
            # base_link velocity in the body frame: CoG velocity + r x offset
            vx = vm * math.cos(b)
            vy = vm * math.sin(b) + rr * ox
            ym = yaw[n, c] + 0.5 * dt * rr  # heading at mid-substep
            cm = math.cos(ym)
            sm = math.sin(ym)
            x[n, c] += (vx * cm - vy * sm) * dt
            y[n, c] += (vx * sm + vy * cm) * dt
            yaw[n, c] += rr * dt
            v[n, c] = v1


@njit(cache=True, fastmath=True)
def wrap_angles(yaw):
    N, C = yaw.shape
    for n in range(N):
        for c in range(C):
            a = yaw[n, c]
            if a > math.pi or a < -math.pi:
                yaw[n, c] = (a + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, fastmath=True)
def nearest_index(px, py, cl, idx, window_back, window_fwd):
    """Update each car's index into the dense centerline table by a local search."""
    N, C = px.shape
    K = cl.shape[0]
    for n in range(N):
        for c in range(C):
            best = 1e30
            bi = idx[n, c]
            i0 = idx[n, c]
            for k in range(-window_back, window_fwd + 1):
                i = (i0 + k) % K
                dx = cl[i, 0] - px[n, c]
                dy = cl[i, 1] - py[n, c]
                d = dx * dx + dy * dy
                if d < best:
                    best = d
                    bi = i
            idx[n, c] = bi


@njit(cache=True, fastmath=True)
def global_nearest(px, py, cl):
    """Index of the nearest dense-centerline point (full search; used at resets)."""
    best = 1e30
    bi = 0
    for i in range(cl.shape[0]):
        dx = cl[i, 0] - px
        dy = cl[i, 1] - py
        d = dx * dx + dy * dy
        if d < best:
            best = d
            bi = i
    return bi


@njit(cache=True, fastmath=True)
def pure_pursuit(x, y, yaw, v, active, idx, offset, vfac, cl, ds, wheelbase, steer_gain, v_max,
                 a_lat, width, first, direction, out):
    """Traffic driver: pure pursuit of the centerline (shifted by each car's lateral offset),
    speed from a per-car fraction of top speed, slowed for curvature ahead and for a car ahead
    driving the same way.

    :param cl: (K, 4) dense centerline table x, y, yaw, curvature at spacing ``ds``.
    :param first: index of the first driven car (1: car 0 is the agent).
    :param direction: 1 along the centerline, -1 against it (the planner's reversed ego).
    :param out: (N, C, 2) normalised actions (a_T, a_delta) written for cars >= first.
    """
    N, C = x.shape
    K = cl.shape[0]
    for n in range(N):
        for c in range(first, C):
            if not active[n, c]:
                continue
            vc = v[n, c]
            ld = 0.6 + 0.4 * vc
            k = (idx[n, c] + direction * int(ld / ds)) % K
            nx = -math.sin(cl[k, 2])
            ny = math.cos(cl[k, 2])
            tx = cl[k, 0] + offset[n, c] * nx
            ty = cl[k, 1] + offset[n, c] * ny
            ca = math.cos(yaw[n, c])
            sa = math.sin(yaw[n, c])
            # from the rear axle (pure pursuit geometry)
            rx = x[n, c] - 0.5 * wheelbase * ca
            ry = y[n, c] - 0.5 * wheelbase * sa
            lx = ca * (tx - rx) + sa * (ty - ry)
            ly = -sa * (tx - rx) + ca * (ty - ry)
            l2 = lx * lx + ly * ly
            delta = math.atan(2.0 * wheelbase * ly / max(l2, 1e-6))
            # speed: slow for the sharpest curvature within the next 2 m + braking distance
            kap = 0.0
            horizon = int((1.0 + vc * vc / 2.0) / ds) + 1
            for h in range(0, horizon, 2):
                kk = abs(cl[(idx[n, c] + direction * h) % K, 3])
                if kk > kap:
                    kap = kk
            vd = vfac[n, c] * v_max
            if kap > 1e-6:
                vd = min(vd, math.sqrt(a_lat / kap))
            # a car ahead in the lane, driving the same way (an oncoming car, e.g. the agent in
            # the reversed heading, is not braked for: as in the PyBullet traffic driver)
            for j in range(C):
                if j == c or not active[n, j] or math.cos(yaw[n, j] - yaw[n, c]) <= 0.0:
                    continue
                ox = ca * (x[n, j] - x[n, c]) + sa * (y[n, j] - y[n, c])
                oy = -sa * (x[n, j] - x[n, c]) + ca * (y[n, j] - y[n, c])
                if ox > 0.0 and ox < 1.5 + vc and abs(oy) < 1.2 * width:
                    vd = min(vd, max(0.0, (ox - 0.8) * 1.2))
            out[n, c, 0] = min(1.0, max(-1.0, vd / v_max + 2.0 * (vd - vc)))
            out[n, c, 1] = min(1.0, max(-1.0, delta / steer_gain))


@njit(cache=True)
def place_world(n, x, y, yaw, v, w, delta, idx, offset, vfac, active, cl, ds, u, n_cars,
                reversed_agent, lat_max, yaw_noise, vfac_lo, vfac_hi):
    """Place the cars of world ``n`` evenly spread (with jitter) along the centerline.

    :param u: uniform random numbers in [0, 1), at least 1 + 5 * C of them (C = slots per world).
    :param n_cars: cars present (agent + obstacles); the rest of the slots are deactivated.
    """
    K = cl.shape[0]
    C = x.shape[1]
    s0 = u[0] * K
    gap = K / n_cars
    for c in range(C):
        if c >= n_cars:
            active[n, c] = False
            x[n, c] = 1e6 + 10.0 * c  # far away: never seen, never touched
            y[n, c] = 1e6
            v[n, c] = 0.0
            w[n, c] = 0.0
            continue
        active[n, c] = True
        k = int(s0 + gap * c + (u[1 + 5 * c] - 0.5) * 0.4 * gap) % K
        off = (2.0 * u[2 + 5 * c] - 1.0) * lat_max
        nx = -math.sin(cl[k, 2])
        ny = math.cos(cl[k, 2])
        x[n, c] = cl[k, 0] + off * nx
        y[n, c] = cl[k, 1] + off * ny
        yaw_c = cl[k, 2] + (2.0 * u[3 + 5 * c] - 1.0) * yaw_noise
        if c == 0 and reversed_agent:
            yaw_c += math.pi
        yaw[n, c] = (yaw_c + math.pi) % (2.0 * math.pi) - math.pi
        v[n, c] = 0.0
        w[n, c] = 0.0
        delta[n, c] = 0.0
        idx[n, c] = k
        offset[n, c] = (2.0 * u[4 + 5 * c] - 1.0) * lat_max * 0.6
        vfac[n, c] = vfac_lo + (vfac_hi - vfac_lo) * u[5 + 5 * c]


@njit(cache=True)
def respawn_car(n, c, x, y, yaw, v, w, delta, idx, offset, active, cl, u, min_dist,
                min_dist_agent, lat_max):
    """Move car c of world n to a random centerline point at least ``min_dist`` from every other
    car and ``min_dist_agent`` from the agent (car 0; a car must not pop up in front of it);
    tries the candidates in ``u`` in turn ((T, 2) uniforms). Returns True if placed."""
    K = cl.shape[0]
    C = x.shape[1]
    for t in range(u.shape[0]):
        k = int(u[t, 0] * K) % K
        off = (2.0 * u[t, 1] - 1.0) * lat_max * 0.6
        px = cl[k, 0] - math.sin(cl[k, 2]) * off
        py = cl[k, 1] + math.cos(cl[k, 2]) * off
        ok = True
        for j in range(C):
            if j == c or not active[n, j]:
                continue
            dx = x[n, j] - px
            dy = y[n, j] - py
            dmin = min_dist_agent if j == 0 else min_dist
            if dx * dx + dy * dy < dmin * dmin:
                ok = False
                break
        if ok:
            x[n, c] = px
            y[n, c] = py
            yaw[n, c] = cl[k, 2]
            v[n, c] = 0.0
            w[n, c] = 0.0
            delta[n, c] = 0.0
            idx[n, c] = k
            offset[n, c] = off
            return True
    return False
