"""The GLSL ``surface_color`` of a sample world: deterministic colour at every world point.

Colour depends only on world position, normal, pattern uv, vertex colour and material id (see
:mod:`gtkit.synth.world`), never on the camera, so the same spot looks the same in every photo
(up to lighting) and in the baked reference texture. Noise octaves finer than twice the pixel
footprint (``fwidth(p)``) fade to their mean, so renders are band-limited at any distance.

The world's own octaves end at about 3 cm (the finest at full contrast ~12 cm), enough for every
camera of the small to large presets (their sharpest pixel, the zoom's, covers >= 2 cm). A preset
whose sharpest camera resolves finer (the full-size preset's 20 MP zoom: 4-8 mm a pixel) also gets
``_MICRO``: four more octaves of grain, 6 cm down to 7.5 mm, multiplied onto every surface but the
GCP targets, band-limited the same way (zero wherever a pixel covers 3 cm or more). Presets without
it compile the very same shader source as before.
"""
from __future__ import annotations

from .world import World

_COMMON = r"""
float h12(vec2 p) {
    vec3 p3 = fract(vec3(p.xyx) * 0.1031);
    p3 += dot(p3, p3.yzx + 33.33);
    return fract((p3.x + p3.y) * p3.z);
}
float vnoise(vec2 p) {
    vec2 i = floor(p); vec2 f = fract(p);
    vec2 u = f * f * (3.0 - 2.0 * f);
    return mix(mix(h12(i), h12(i + vec2(1, 0)), u.x), mix(h12(i + vec2(0, 1)), h12(i + vec2(1, 1)), u.x), u.y);
}
// band-limited fbm: wavelengths from wl0 down, halving; fp = pixel footprint (m)
float fbm(vec2 p, float wl0, int oct, float fp, float gainv) {
    float s = 0.0, a = 1.0, wsum = 0.0, wl = wl0;
    for (int i = 0; i < oct; i++) {
        float fade = clamp((wl / max(fp, 1e-4) - 2.0) * 0.5, 0.0, 1.0);
        float n = vnoise(p / wl + vec2(17.3 * float(i), 5.1 * float(i)));
        s += a * mix(0.5, n, fade);
        wsum += a; a *= gainv; wl *= 0.5;
    }
    return clamp(0.5 + (s / wsum - 0.5) * 2.0, 0.0, 1.0);   // stretch: sums of octaves are flat
}
vec2 planar(vec3 p, vec3 n) {
    vec3 a = abs(n);
    if (a.z >= a.x && a.z >= a.y) return p.xy;
    if (a.x >= a.y) return vec2(p.y, p.z);
    return vec2(p.x, p.z);
}
// sparse blobs (stones, bushes, stains) of one size; fades out below the pixel footprint
float blobs(vec2 q, float wl, float fp, float thr) {
    float fade = clamp((wl / max(fp, 1e-4) - 2.0) * 0.5, 0.0, 1.0);
    return fade * smoothstep(thr, thr + 0.06, vnoise(q / wl));
}
vec3 clutter(vec3 c, vec2 q, float fp, float k) {
    float d = blobs(q + 31.7, 0.6, fp, 0.73) + blobs(q + 13.1, 1.4, fp, 0.75) + blobs(q - 7.7, 3.2, fp, 0.77);
    float l = blobs(q + 5.3, 0.9, fp, 0.75) + blobs(q + 2.9, 2.2, fp, 0.78);
    return c * (1.0 - k * 0.4 * min(d, 1.0)) + k * vec3(0.22, 0.20, 0.17) * min(l, 1.0);
}
float seg_dist(vec2 p, vec4 s, out float along) {
    vec2 d = s.zw - s.xy;
    float L = length(d);
    float t = clamp(dot(p - s.xy, d) / (L * L), 0.0, 1.0);
    along = t * L;
    return length(p - (s.xy + t * d));
}
"""

_MAIN = r"""
vec3 terrain_color(vec3 p, float fp) {
    vec2 q = p.xy;
    float fine = fbm(q, 4.0, 8, fp, 0.8);
    // roads
    float best = 1e9, along = 0.0, hw = 0.0;
    for (int i = 0; i < N_ROADS; i++) {
        float a;
        float d = seg_dist(q, ROADS[i], a) - ROAD_HW[i];
        if (d < best) { best = d; along = a; hw = ROAD_HW[i]; }
    }
    if (best < 0.0) {
        float dc = best + hw;                       // distance to the centre line
        vec3 c = vec3(0.30, 0.30, 0.32) * (0.75 + 0.5 * fine);
        float crack = fbm(q * 1.0, 0.5, 4, fp, 0.9);
        c = clutter(c * (0.9 + 0.2 * crack), q * 1.3, fp, 0.5);
        bool dash = dc < 0.12 && fract(along / 6.0) < 0.5;
        bool edge = best > -0.45 && best < -0.3;
        if (dash || edge) c = vec3(0.92, 0.92, 0.88) * (0.9 + 0.1 * fine);
        return c;
    }
    // lake: very low texture
    vec2 e = (q - LAKE.xy) / LAKE.zw;
    float r = length(e);
    if (HAS_LAKE && r < 1.0) {
        float ripple = fbm(q, 8.0, 3, fp, 0.5);
        return mix(vec3(0.16, 0.26, 0.30), vec3(0.20, 0.30, 0.32), ripple) * (r > 0.97 ? 1.3 : 1.0);
    }
    if (HAS_LAKE && r < 1.08) return vec3(0.55, 0.50, 0.40) * (0.8 + 0.4 * fine);   // shore
    float curb = best < 0.25 ? 1.25 : 1.0;                                          // kerb stones
    bool inside = max(abs(q.x), abs(q.y)) < HALF;
    if (q.x > TOWN_X0 && inside) {
        // town ground: paving tiles with grass patches
        float grass = fbm(q, 24.0, 3, fp, 0.5);
        vec2 tile = fract(q / 0.6);
        float joint = (min(tile.x, tile.y) < 0.06 && fp < 0.15) ? 0.75 : 1.0;
        vec3 pave = vec3(0.62, 0.60, 0.56) * (0.8 + 0.4 * fine) * joint
                    * (0.9 + 0.2 * h12(floor(q / 0.6)));
        vec3 lawn = vec3(0.30, 0.45, 0.20) * (0.7 + 0.6 * fine);
        return clutter(mix(pave, lawn, smoothstep(0.55, 0.6, grass)) * curb, q, fp, 1.0);
    }
    // rural: fields with crop rows, grass margins
    vec2 cell = floor(q / FIELD + vec2(0.3, 0.7));
    vec2 fq = fract(q / FIELD + vec2(0.3, 0.7));
    float k = h12(cell + 3.7);
    float margin = min(min(fq.x, 1.0 - fq.x), min(fq.y, 1.0 - fq.y)) * FIELD;
    vec3 grass = vec3(0.33, 0.46, 0.21) * (0.65 + 0.7 * fine);
    if (margin < 1.5 || k < 0.2) return clutter(grass * curb, q, fp, 1.0);
    vec3 crop = k < 0.45 ? vec3(0.55, 0.58, 0.25) : (k < 0.7 ? vec3(0.45, 0.36, 0.24) : vec3(0.26, 0.50, 0.22));
    float ang = h12(cell + 9.1) * 3.14159;
    float row = 0.5 + 0.5 * sin(dot(q, vec2(cos(ang), sin(ang))) * 6.2832 / 0.75);
    float rowfade = clamp((0.75 / max(fp, 1e-4) - 2.0) * 0.5, 0.0, 1.0);
    return clutter(crop * (0.7 + 0.5 * fine) * (1.0 + 0.25 * rowfade * (row - 0.5)), q, fp, 0.8);
}

vec3 wall_color(vec3 p, vec3 n, vec2 uv, vec3 col, float fp) {
    float fine = fbm(planar(p, n), 2.0, 7, fp, 0.8);
    vec3 c = col * (0.82 + 0.3 * fine);
    float fx = fract(uv.x / 3.0), fy = fract((uv.y - 0.3) / 3.2);
    float floor_i = floor((uv.y - 0.3) / 3.2);
    if (uv.y > 1.0 && fx > 0.22 && fx < 0.78 && fy > 0.3 && fy < 0.78) {
        float lit = h12(vec2(floor(uv.x / 3.0), floor_i) + col.xy * 91.0);
        c = mix(vec3(0.10, 0.14, 0.20), vec3(0.35, 0.42, 0.50), lit) * (0.85 + 0.3 * fine);
        if (abs(fx - 0.5) < 0.02) c *= 0.5;   // mullion
    } else if (fy > 0.9 && uv.y > 1.0) {
        c *= 0.8;                                // floor band
    }
    return c;
}

vec3 roof_color(vec3 p, vec2 uv, float fp, bool tiles) {
    float fine = fbm(p.xy, 3.0, 8, fp, 0.82);
    if (tiles) {
        float row = fract(uv.y / 0.32);
        float off = fract(uv.x / 0.25 + 0.5 * floor(uv.y / 0.32));
        float shade = (row < 0.15 || off < 0.06) && fp < 0.1 ? 0.7 : 1.0;
        return vec3(0.55, 0.25, 0.18) * (0.75 + 0.5 * fine) * shade;
    }
    vec3 c = clutter(vec3(0.55, 0.55, 0.53) * (0.7 + 0.6 * fine), uv, fp, 0.8);
    vec2 cell = floor(uv / 4.0);
    vec2 f = fract(uv / 4.0);
    if (h12(cell + 1.3) < 0.15 && max(abs(f.x - 0.5), abs(f.y - 0.5)) < 0.3) c = vec3(0.8, 0.8, 0.78) * (0.9 + 0.2 * fine);
    return c;
}

vec3 tree_color(vec3 p, vec3 n, float fp) {
    float clump = fbm(planar(p, n) + p.z * 0.37, 2.0, 7, fp, 0.85);
    return vec3(0.16, 0.33, 0.12) * (0.5 + 1.0 * clump);
}

vec3 gcp_color(vec2 uv) {
    // checker quadrants in a white border, analytically anti-aliased over the pixel footprint
    // so the centre (an X-corner) is where a camera integrating light would see it
    float h = GCP_HALF;
    vec2 fw = max(fwidth(uv), vec2(1e-4));
    float inner = clamp((0.82 * h - max(abs(uv.x), abs(uv.y))) / max(fw.x, fw.y) + 0.5, 0.0, 1.0);
    float sx = clamp(uv.x / fw.x, -0.5, 0.5) * 2.0;
    float sy = clamp(uv.y / fw.y, -0.5, 0.5) * 2.0;
    float dark = 0.5 + 0.5 * sx * sy;                                       // 1 in the ++ and -- quadrants
    vec3 checker = mix(vec3(0.97), vec3(0.05), dark);
    return mix(vec3(0.95), checker, inner);
}

vec3 surface_color(vec3 p, vec3 n, vec2 uv, vec3 col, float mat) {
    float fp = max(length(fwidth(p)), 1e-4);
    int m = int(mat + 0.5);
    if (m == 0) return terrain_color(p, fp);
    if (m == 1) return wall_color(p, n, uv, col, fp);
    if (m == 2) return roof_color(p, uv, fp, false);
    if (m == 3) return roof_color(p, uv, fp, true);
    if (m == 4) return tree_color(p, n, fp);
    if (m == 5) return gcp_color(uv);
    return col;
}
"""


_MICRO = r"""
// grain below the world's own octaves (6 cm .. 7.5 mm), zero where a pixel covers >= 3 cm
float micro_grain(vec2 q, float fp) {
    float s = 0.0, a = 1.0, wl = 0.06;
    for (int i = 0; i < 4; i++) {
        float fade = clamp((wl / max(fp, 1e-4) - 2.0) * 0.5, 0.0, 1.0);
        s += a * fade * (vnoise(q / wl + vec2(3.1 * float(i), 7.7 * float(i))) - 0.5);
        a *= 0.85; wl *= 0.5;
    }
    return s;
}
vec3 surface_color(vec3 p, vec3 n, vec2 uv, vec3 col, float mat) {
    vec3 c = surface_color_base(p, n, uv, col, mat);
    int m = int(mat + 0.5);
    if (m > 4) return c;
    float fp = max(length(fwidth(p)), 1e-4);
    return c * (1.0 + MICRO_AMP * micro_grain(planar(p, n) + (m == 0 ? vec2(0.0) : vec2(0.0, p.z * 0.37)), fp));
}
"""
MICRO_BELOW_M = 0.015   # a preset whose sharpest camera's pixel covers less than this gets _MICRO
MICRO_AMP = 0.9         # the grain's contrast (its four octaves sum to about +-0.3 of the colour)


def finest_footprint_m(s) -> float:
    """Nominal ground footprint (m) of the sharpest pixel any camera of settings ``s`` takes: the
    reference at its altitude, wide and zoom at the lowest sequence's height (ranges are longer)."""
    import numpy as np

    def fx(width, hfov):
        return width / 2.0 / np.tan(np.radians(hfov) / 2.0)
    r, q = s.reference, s.queries
    out = r.altitude_agl / fx(r.width, r.hfov_deg)
    if q.sequences:
        h = min(seq.height_agl for seq in q.sequences)
        out = min(out, h / fx(q.wide_width, q.wide_hfov_deg), h / fx(q.zoom_width, q.zoom_hfov_deg))
    return float(out)


def _f(v: float) -> str:
    return f"{float(v):.6f}"


def world_glsl(world: World, field_m: float = 40.0, micro: bool = False) -> str:
    """The GLSL source for a world (its roads, lake and town edge are compiled in); ``micro`` adds
    the grain below 3 cm (:data:`_MICRO`; see the module doc)."""
    roads = world.roads
    lake = world.lake or (0.0, 0.0, 1.0, 1.0, 0.0)
    consts = [
        f"const int N_ROADS = {len(roads)};",
        "const vec4 ROADS[N_ROADS] = vec4[N_ROADS](" + ", ".join(
            f"vec4({_f(a)}, {_f(b)}, {_f(c)}, {_f(d)})" for a, b, c, d, _ in roads) + ");",
        "const float ROAD_HW[N_ROADS] = float[N_ROADS](" + ", ".join(_f(r[4]) for r in roads) + ");",
        f"const vec4 LAKE = vec4({_f(lake[0])}, {_f(lake[1])}, {_f(lake[2])}, {_f(lake[3])});",
        f"const bool HAS_LAKE = {'true' if world.lake else 'false'};",
        f"const float TOWN_X0 = {_f(world.town_x0)};",
        f"const float FIELD = {_f(field_m)};",
        f"const float HALF = {_f(world.size / 2)};",
        f"const float GCP_HALF = {_f(world.gcp_size / 2)};",
    ]
    if micro:
        consts.append(f"const float MICRO_AMP = {_f(MICRO_AMP)};")
        main = _MAIN.replace("vec3 surface_color(vec3 p, vec3 n, vec2 uv, vec3 col, float mat) {",
                             "vec3 surface_color_base(vec3 p, vec3 n, vec2 uv, vec3 col, float mat) {")
        return _COMMON + "\n".join(consts) + "\n" + main + _MICRO
    return _COMMON + "\n".join(consts) + "\n" + _MAIN
