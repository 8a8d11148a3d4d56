"""Sun shadows: where the sun stands, how far shadows reach, and the sun-space frame of shadow maps.

The sun is an azimuth (degrees clockwise from north, where the sun stands) and an elevation
(degrees above the horizon): given in the config, or computed from a date, time and place with
astral (NOAA's algorithm, apparent elevation: refraction included).

Sun space is one frame for the whole scene: each point is slid along its sun ray down to the
plane z = 0, (x, y) − z·cot(elevation)·(sin azimuth, cos azimuth), and keeps its height as depth
(the highest point of a ray is the one the sun reaches). This parallel projection along the
light is what an orthographic camera looking from the sun sees, on a sheared frame whose texels
are squares of level ground aligned with the map: a tile's shadow map covers little more than
its own ground, and texel (k, l) covers [k·t, (k+1)·t) × [l·t, (l+1)·t) of that plane, one
global grid, so every tile's shadow map samples the same rays and adjacent tiles compute the same
shadow for the same point (no seams). All float64; only the final matrices go to the GPU as float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from pipeline25d.core.errors import ConfigError

PCF_RADIUS = 1.0          # texels: radius of the tent filter over depth comparisons (bilinear: 2 x 2 taps)
BIAS_TEXELS = 0.5         # height bias in texels (metres of height per texel edge): light may leak
                          # bias·cot(elevation) at a wall's foot, half a texel at 45°
WINDOW_PAD = 2            # texels around the receivers: the filter's taps stay inside the map
DEPTH_MARGIN_M = 1.0      # keeps casters and receivers off the shadow map's near and far planes
CENTRE_STEP_DEG = 0.01    # the scene centre that places the sun, rounded (~1 km; the sun moves by hundredths
                          # of a degree)


@dataclass(frozen=True)
class Sun:
    """The sun's position: azimuth (degrees clockwise from north) and elevation (degrees, (0, 90])."""

    azimuth: float
    elevation: float

    def toward(self) -> np.ndarray:
        """(3,) unit vector from the ground toward the sun (scene axes: x east, y north, z up)."""
        a, e = math.radians(self.azimuth), math.radians(self.elevation)
        return np.array([math.sin(a) * math.cos(e), math.cos(a) * math.cos(e), math.sin(e)])

    def away(self) -> np.ndarray:
        """(2,) unit horizontal direction in which shadows fall (away from the sun)."""
        a = math.radians(self.azimuth)
        return -np.array([math.sin(a), math.cos(a)])

    def reach(self, height: float | np.ndarray) -> float | np.ndarray:
        """Horizontal length (m) of the shadow of ``height`` metres: height·cot(elevation)."""
        if self.elevation >= 90:
            return 0.0 * height
        return height / math.tan(math.radians(self.elevation))


def sun_position(when: datetime, lon: float, lat: float) -> Sun:
    """The sun seen from (lon, lat) (WGS 84 degrees) at ``when`` (time-zone aware), by astral:
    azimuth and apparent elevation (refraction included), degrees."""
    from astral import Observer
    from astral.sun import azimuth, elevation

    observer = Observer(latitude=lat, longitude=lon)
    return Sun(float(azimuth(observer, when)), float(elevation(observer, when, with_refraction=True)))


def parse_datetime(text: str) -> datetime:
    """An ISO 8601 date and time with its zone; ConfigError naming ``shadows.datetime`` otherwise."""
    try:
        when = datetime.fromisoformat(str(text))
    except ValueError:
        raise ConfigError(f"config key shadows.datetime: {text!r} is no ISO 8601 date and time "
                          "(e.g. 2024-06-21T15:00:00+02:00)") from None
    if when.tzinfo is None or when.utcoffset() is None:
        raise ConfigError(f"config key shadows.datetime: {text!r} has no time zone (add e.g. +02:00 or Z)")
    return when


def check_sun_config(cfg: dict) -> None:
    """Checks of the ``shadows`` block beyond the schema: the sun given one way, a parseable time;
    with a place, the sun above the horizon then."""
    if not cfg.get("enabled"):
        return
    given = [k for k in ("azimuth", "elevation") if k in cfg]
    if "datetime" in cfg and given:
        raise ConfigError("config key shadows: give the sun as azimuth and elevation or as datetime "
                          f"(with an optional place), not both (got datetime and {', '.join(given)})")
    if "datetime" not in cfg:
        if len(given) < 2:
            missing = " and ".join(k for k in ("azimuth", "elevation") if k not in cfg)
            raise ConfigError(f"config key shadows: shadows are enabled but the sun is not given: add {missing} "
                              "(degrees) or datetime (ISO 8601 with zone)")
        if "place" in cfg:
            raise ConfigError("config key shadows.place: a place only serves datetime; with azimuth and "
                              "elevation leave it out")
        return
    when = parse_datetime(cfg["datetime"])
    if "place" in cfg:
        resolve_sun(cfg, (cfg["place"]["lon"], cfg["place"]["lat"]), when)


def resolve_sun(cfg: dict, centre_lonlat: tuple[float, float] | None = None, when: datetime | None = None) -> Sun:
    """The configured sun: azimuth and elevation as given, or computed from ``datetime`` at ``place``
    (default: ``centre_lonlat``, the scene centre). ConfigError when the sun is not above the horizon."""
    if "datetime" not in cfg:
        return Sun(float(cfg["azimuth"]), float(cfg["elevation"]))
    when = when or parse_datetime(cfg["datetime"])
    if "place" in cfg:
        lon, lat, where = cfg["place"]["lon"], cfg["place"]["lat"], "shadows.place"
    elif centre_lonlat is not None:
        (lon, lat), where = centre_lonlat, "the scene centre"
    else:
        raise ConfigError("config key shadows.place: needed to place the sun (no scene centre known here)")
    sun = sun_position(when, lon, lat)
    if sun.elevation <= 0:
        raise ConfigError(f"config key shadows.datetime: the sun is {-sun.elevation:.1f}° below the horizon at "
                          f"{cfg['datetime']} seen from lon {lon:.4f}, lat {lat:.4f} ({where}); no shadows to cast")
    return sun


def plan_shadows(cfg: dict, scene_bounds: np.ndarray, crs: str, gsd: float) -> dict:
    """The shadow settings a plan records (and its tiles' spec hashes cover): the sun resolved
    (``datetime`` without ``place`` is seen from the scene centre, rounded to CENTRE_STEP_DEG so
    that a district update rarely moves the sun, and with it every tile), texel size, filter and bias."""
    from pipeline25d.core.crs import transform_points

    lo, hi = np.asarray(scene_bounds, dtype=np.float64)
    centre = np.round(transform_points(((lo + hi) / 2)[None], crs, "EPSG:4326")[0] / CENTRE_STEP_DEG) * CENTRE_STEP_DEG
    sun = resolve_sun(cfg, (round(float(centre[0]), 6), round(float(centre[1]), 6)))
    texel = float(cfg["texel_px"]) * gsd
    source = ("azimuth and elevation" if "datetime" not in cfg else
              f"{cfg['datetime']} at " + (f"lon {cfg['place']['lon']}, lat {cfg['place']['lat']}" if "place" in cfg
                                          else f"the scene centre (lon {centre[0]:.2f}, lat {centre[1]:.2f})"))
    return {"azimuth": round(sun.azimuth, 4), "elevation": round(sun.elevation, 4), "source": source,
            "texel": texel, "ambient": float(cfg["ambient"]), "radius": PCF_RADIUS, "bias": BIAS_TEXELS * texel}


# -- sun space -------------------------------------------------------------------------------
@dataclass(frozen=True)
class SunFrame:
    """The scene's sun space (see the module): the sun and the texel edge ``texel`` (metres of level ground)."""

    sun: Sun
    texel: float

    def to_texels(self) -> np.ndarray:
        """3×3: scene metres -> (u, w) texels of the plane z = 0 along the sun rays, and depth −z (m)."""
        shift = -self.sun.away() * float(self.sun.reach(1.0))      # (x, y) moves by −z·cot(e)·(sin a, cos a)
        t = 1.0 / self.texel
        return np.array([[t, 0.0, -shift[0] * t], [0.0, t, -shift[1] * t], [0.0, 0.0, -1.0]])

    def project(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) scene points -> (n, 3) float64 [u, w] in global texels and depth (m, −height)."""
        return np.asarray(points, dtype=np.float64) @ self.to_texels().T

    def per_texel(self) -> tuple[np.ndarray, np.ndarray]:
        """Scene-metre steps of one texel along u and along w at constant depth, each divided by
        −(sun · the step of one metre of depth): the depth a plane of normal n gains per texel is then
        n·step / n·sun (the receiver-plane offset of the filter's comparisons)."""
        steps = np.linalg.inv(self.to_texels())
        scale = -1.0 / float(self.sun.toward() @ steps[:, 2])
        return steps[:, 0] * scale, steps[:, 1] * scale

    def ground_margin(self) -> float:
        """Horizontal metres (along x and along y) within which the filter's taps around a point meet
        other sun rays: (radius + pad) texels."""
        return (PCF_RADIUS + WINDOW_PAD) * self.texel

    def window(self, boxes: list[np.ndarray]) -> tuple[int, int, int, int]:
        """Global texel range (k0, l0, k1, l1), end exclusive, holding (2, 3) boxes plus WINDOW_PAD texels."""
        corners = np.vstack([_corners(b) for b in boxes])
        uw = self.project(corners)[:, :2]
        lo, hi = np.floor(uw.min(axis=0)).astype(int) - WINDOW_PAD, np.ceil(uw.max(axis=0)).astype(int) + WINDOW_PAD
        return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])

    def depth_range(self, boxes: list[np.ndarray]) -> tuple[float, float]:
        """Depth range (m, −height) of (2, 3) boxes, with DEPTH_MARGIN_M on both ends."""
        d = self.project(np.vstack([_corners(b) for b in boxes]))[:, 2]
        return float(d.min()) - DEPTH_MARGIN_M, float(d.max()) + DEPTH_MARGIN_M

    def lookup_matrix(self, window: tuple[int, int, int, int], depth_range: tuple[float, float],
                      origin: np.ndarray) -> np.ndarray:
        """4×4 float64: chunk-local (scene point − origin) -> (u − k0, w − l0) texels and depth − near (m).
        The translation is computed relative to ``origin`` in float64, so float32 keeps it exact."""
        m = np.eye(4)
        m[:3, :3] = self.to_texels()
        at = self.project(np.asarray(origin, dtype=np.float64)[None])[0]
        m[:3, 3] = at - np.array([window[0], window[1], depth_range[0]])
        return m

    def clip_matrix(self, window: tuple[int, int, int, int], depth_range: tuple[float, float],
                    origin: np.ndarray) -> np.ndarray:
        """4×4 float64: chunk-local coordinates -> GL clip space of the shadow map (window onto NDC [-1, 1],
        depth range onto [-1, 1]): texel (k, l)'s centre is its pixel's centre."""
        w, h = window[2] - window[0], window[3] - window[1]
        scale = np.diag([2.0 / w, 2.0 / h, 2.0 / (depth_range[1] - depth_range[0]), 1.0])
        shift = np.eye(4)
        shift[:3, 3] = -1.0
        return shift @ scale @ self.lookup_matrix(window, depth_range, origin)


def _corners(box: np.ndarray) -> np.ndarray:
    lo, hi = np.asarray(box, dtype=np.float64)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


# -- shadow reach (the plan) ------------------------------------------------------------------
def shadow_footprints(bounds: np.ndarray, sun: Sun, margin: float = 0.0) -> np.ndarray:
    """(n, 4) [xmin, ymin, xmax, ymax]: the ground each (n, 2, 3) chunk box can shadow.

    A chunk's shadow falls away from the sun at most (z_max − z_low)·cot(elevation) from its box,
    z_low the lowest geometry it can reach: the lowest floor of the chunks (their boxes grown by
    ``margin``) that its swept footprint meets, found by iteration (z_low only falls, and there
    are finitely many chunks)."""
    bounds = np.asarray(bounds, dtype=np.float64)
    xy = np.column_stack([bounds[:, 0, :2], bounds[:, 1, :2]])
    grown = xy + np.array([-margin, -margin, margin, margin])
    floors = bounds[:, 0, 2]
    out = xy.copy()
    for i in range(len(bounds)):
        low = floors[i]
        while True:
            out[i] = _swept(xy[i], sun.away() * sun.reach(bounds[i, 1, 2] - low))
            lowest = floors[_overlapping(grown, out[i])].min()
            if lowest >= low:
                break
            low = lowest
    return out


def _swept(box: np.ndarray, v: np.ndarray) -> np.ndarray:
    """[xmin, ymin, xmax, ymax] of a box and the box moved by v (the box swept along v)."""
    return np.array([box[0] + min(v[0], 0.0), box[1] + min(v[1], 0.0), box[2] + max(v[0], 0.0),
                     box[3] + max(v[1], 0.0)])


def _overlapping(boxes: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(n,) bool: which [xmin, ymin, xmax, ymax] boxes meet ``box`` (touching counts)."""
    return ((boxes[:, 0] <= box[2]) & (boxes[:, 2] >= box[0]) & (boxes[:, 1] <= box[3]) & (boxes[:, 3] >= box[1]))


def casters_of(footprints: np.ndarray, receivers: list[np.ndarray], margin: float) -> np.ndarray:
    """(n,) bool: chunks whose shadow footprint meets a receiver's xy box ((2, 3) boxes) grown by ``margin``."""
    hit = np.zeros(len(footprints), dtype=bool)
    for box in receivers:
        grown = np.array([box[0][0] - margin, box[0][1] - margin, box[1][0] + margin, box[1][1] + margin])
        hit |= _overlapping(footprints, grown)
    return hit
