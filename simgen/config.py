"""Frozen configuration dataclasses, one per stage, and strict YAML preset loading.

A preset is a YAML file in ``scenes/`` (or any path). Loading is strict: an unknown key, a
wrong type or an out-of-range value raises :class:`ConfigError` with one line that names the
file, the dotted field and the allowed range. Keys left out take the defaults below.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

import yaml

from .errors import ConfigError

PRESET_DIR = Path(__file__).resolve().parent.parent / "scenes"


def allowed(lo=None, hi=None, choices=None) -> dict:
    """Field metadata: the allowed range (inclusive) or the allowed choices."""
    return {"lo": lo, "hi": hi, "choices": choices}


@dataclass(frozen=True)
class LayoutConfig:
    """The road grid. Road centrelines are ``block_pitch`` apart in x and y."""
    blocks_x: int = field(default=3, metadata=allowed(1, 12))
    blocks_y: int = field(default=3, metadata=allowed(1, 12))
    block_pitch: float = field(default=90.0, metadata=allowed(40.0, 300.0))
    lanes_per_direction: int = field(default=2, metadata=allowed(1, 3))
    lane_width: float = field(default=3.5, metadata=allowed(2.5, 4.5))
    parking_width: float = field(default=2.5, metadata=allowed(2.0, 3.5))
    sidewalk_width: float = field(default=5.0, metadata=allowed(3.0, 8.0))
    building_height: tuple[float, float] = field(default=(6.0, 30.0), metadata=allowed(3.0, 200.0))
    building_gap: tuple[float, float] = field(default=(1.0, 8.0), metadata=allowed(0.0, 50.0))
    clutter_spacing: float = field(default=14.0, metadata=allowed(4.0, 100.0))


@dataclass(frozen=True)
class ActorsConfig:
    """Actor densities. "per_km" counts are per km of road centreline."""
    parked_fraction: float = field(default=0.55, metadata=allowed(0.0, 1.0))
    vehicles_per_km: float = field(default=22.0, metadata=allowed(0.0, 200.0))
    vehicle_mix: dict = field(default_factory=lambda: {
        "car": 0.82, "truck": 0.07, "bus": 0.04, "motorcycle": 0.07})
    pedestrians_per_km: float = field(default=70.0, metadata=allowed(0.0, 1000.0))
    standing_fraction: float = field(default=0.3, metadata=allowed(0.0, 1.0))
    crossing_fraction: float = field(default=0.25, metadata=allowed(0.0, 1.0))
    bicycles_per_km: float = field(default=8.0, metadata=allowed(0.0, 200.0))
    parked_bicycles_per_km: float = field(default=10.0, metadata=allowed(0.0, 200.0))
    cones_per_km: float = field(default=8.0, metadata=allowed(0.0, 200.0))
    barriers_per_km: float = field(default=6.0, metadata=allowed(0.0, 200.0))
    stop_probability: float = field(default=0.2, metadata=allowed(0.0, 1.0))
    # Parked trucks' and motorcycles' shares of the parking-strip slots that hold a vehicle.
    parked_truck_fraction: float = field(default=0.06, metadata=allowed(0.0, 1.0))
    parked_motorcycle_fraction: float = field(default=0.06, metadata=allowed(0.0, 1.0))
    # Road works: a curb-lane segment closed by cones and barriers with a construction vehicle.
    construction_zones_per_km: float = field(default=0.0, metadata=allowed(0.0, 50.0))
    # Trailers: the share of moving trucks that tow one, and unhitched ones parked at the curb.
    hitched_trailer_fraction: float = field(default=0.0, metadata=allowed(0.0, 1.0))
    parked_trailers_per_km: float = field(default=0.0, metadata=allowed(0.0, 100.0))
    # The share of moving vehicles (trains included) that turn left or right at an intersection ahead.
    turning_fraction: float = field(default=0.0, metadata=allowed(0.0, 1.0))
    # Bus stops in the parking strips, each with a bus standing at it.
    bus_stops_per_km: float = field(default=0.0, metadata=allowed(0.0, 100.0))


@dataclass(frozen=True)
class EgoConfig:
    """The ego's cruise speed is drawn from ``speed`` (m/s)."""
    speed: tuple[float, float] = field(default=(4.0, 12.0), metadata=allowed(0.0, 15.0))


@dataclass(frozen=True)
class CameraConfig:
    """Six cameras rendered with pyrender. Intrinsics are scaled to ``resolution``."""
    resolution: tuple[int, int] = field(default=(1600, 900), metadata=allowed(16, 4096))
    jpeg_quality: int = field(default=92, metadata=allowed(90, 100))
    ambient: float = field(default=0.45, metadata=allowed(0.0, 2.0))
    sun_intensity: float = field(default=3.0, metadata=allowed(0.0, 20.0))
    zfar: float = field(default=400.0, metadata=allowed(50.0, 5000.0))
    # Cast shadows from the sun in the pyrender cameras (simgen/sun.py); Mitsuba always has them.
    shadows: bool = field(default=True, metadata=allowed(choices=(True, False)))
    # pyrender (rasterised, the default) or mitsuba (path-traced rgb, simgen/mitsuba_camera.py).
    renderer: str = field(default="pyrender", metadata=allowed(choices=("pyrender", "mitsuba")))
    spp: int = field(default=16, metadata=allowed(1, 4096))


@dataclass(frozen=True)
class LidarConfig:
    """HDL-32E: 32 rings from -30.67 to +10.67 deg, 20 Hz rotation."""
    azimuth_step_deg: float = field(default=0.33, metadata=allowed(0.05, 2.0))
    min_range: float = field(default=1.0, metadata=allowed(0.0, 5.0))
    max_range: float = field(default=100.0, metadata=allowed(70.0, 100.0))
    range_noise_sigma: float = field(default=0.02, metadata=allowed(0.0, 0.5))
    # A return is detected when rho * cos(incidence) / R^2 >= min_return (1/m^2): a target of
    # reflectivity 0.05 at normal incidence is seen to 100 m, the asphalt ahead to about 35 m.
    min_return: float = field(default=5e-6, metadata=allowed(0.0, 1.0))
    # Intensity 255 is reached by rho * cos / R^2 >= 1 / intensity_ref_range^2.
    intensity_ref_range: float = field(default=6.0, metadata=allowed(0.5, 100.0))
    # Fog keeps this threshold: a return is lost only when the lidar equation puts it below
    # min_return, and a fog echo replaces it only where stronger (simgen/degrade.py).


SENSOR_CHANNELS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT",
                   "CAM_FRONT_LEFT", "LIDAR_TOP")


@dataclass(frozen=True)
class DegradeConfig:
    """Sensor degradation (simgen/degrade.py). The world and the labels stay the clean ones.

    fog : severity 0-5 (lidar alpha 0, 0.005, 0.01, 0.02, 0.03, 0.06 /m), or fog_visibility :
    the meteorological optical range in metres (> 0 overrides the severity; 0 = off).
    lens_occlusion : 0-5 dirt blobs on every camera. beam_drop : rings removed (of 32).
    lidar_fov : degrees kept around the ego's forward axis (360 = all).
    drop_sensors : comma-separated channels that deliver nothing (black image / empty cloud).
    occlusion : none | light | heavy extra static occluders along the ego's route
    (simgen/occluders.py). Unlike the others it changes the world, hence the annotations'
    visibility and num_lidar_pts (never which objects exist).
    """
    fog: int = field(default=0, metadata=allowed(0, 5))
    fog_visibility: float = field(default=0.0, metadata=allowed(0.0, 100000.0))
    lens_occlusion: int = field(default=0, metadata=allowed(0, 5))
    beam_drop: int = field(default=0, metadata=allowed(0, 32))
    lidar_fov: float = field(default=360.0, metadata=allowed(1.0, 360.0))
    drop_sensors: str = ""
    occlusion: str = field(default="none", metadata=allowed(choices=("none", "light", "heavy")))

    @property
    def alpha(self) -> float:
        """Fog extinction (1/m) shared by camera and lidar; 0 without fog."""
        from .degrade import FOG_ALPHA, alpha_of_visibility
        return alpha_of_visibility(self.fog_visibility) if self.fog_visibility > 0 else FOG_ALPHA[self.fog]

    @property
    def dropped(self) -> tuple[str, ...]:
        return tuple(c for c in (x.strip() for x in self.drop_sensors.split(",")) if c)

    @property
    def active(self) -> bool:
        return self != DegradeConfig()

    def describe(self) -> str:
        """One line for the scene description ('' when clean)."""
        from .degrade import visibility_of
        parts = []
        if self.alpha > 0:
            parts.append(f"fog alpha {self.alpha:.4g}/m (visibility {visibility_of(self.alpha):.0f} m)")
        if self.lens_occlusion:
            parts.append(f"lens occlusion {self.lens_occlusion}")
        if self.beam_drop:
            parts.append(f"{self.beam_drop} of 32 lidar rings dropped")
        if self.lidar_fov < 360:
            parts.append(f"lidar FOV {self.lidar_fov:g} deg")
        if self.dropped:
            parts.append(f"failed sensors {', '.join(self.dropped)}")
        if self.occlusion != "none":
            parts.append(f"{self.occlusion} occlusion")
        return ("Degraded: " + "; ".join(parts) + ".") if parts else ""


@dataclass(frozen=True)
class WeatherConfig:
    """Weather (simgen/weather/; derivations in docs/weather.md). Like the degradation it acts
    on the sensors only: the world, the poses and the labels stay those of the clear day, and
    each model draws from its own seeded stream, so a rainy set pairs with the clean one.

    rain : rain rate in mm/h (0 = none): drops from Marshall-Palmer's size distribution.
    snow : snowfall rate in mm/h of melted water (0 = none): flakes after Gunn and Marshall.
    night : the sun below the horizon, street and vehicle lights, a camera's photon and read
    noise at a night exposure; the lidar, an active sensor, is unchanged.
    """
    rain: float = field(default=0.0, metadata=allowed(0.0, 200.0))
    snow: float = field(default=0.0, metadata=allowed(0.0, 20.0))
    night: bool = False

    @property
    def active(self) -> bool:
        return self != WeatherConfig()

    @property
    def particles(self) -> bool:
        """Rain or snow: the camera models need each pixel's range."""
        return self.rain > 0 or self.snow > 0

    def describe(self) -> str:
        """One line for the scene description ('' in clear weather by day)."""
        parts = []
        if self.rain > 0:
            parts.append(f"rain {self.rain:g} mm/h")
        if self.snow > 0:
            parts.append(f"snowfall {self.snow:g} mm/h water equivalent")
        if self.night:
            parts.append("night")
        return ("Weather: " + "; ".join(parts) + ".") if parts else ""


def check_channels(text: str, where: str) -> None:
    """Refuse unknown sensor channel names in a drop_sensors list."""
    bad = [c for c in (x.strip() for x in text.split(",")) if c and c not in SENSOR_CHANNELS]
    if bad:
        raise ConfigError(f"{where}: unknown channel {bad[0]!r} (allowed: {', '.join(SENSOR_CHANNELS)})")


@dataclass(frozen=True)
class SceneConfig:
    """Everything a preset sets. ``name`` and ``source`` record where it came from."""
    description: str = ""
    layout: LayoutConfig = field(default_factory=LayoutConfig)
    actors: ActorsConfig = field(default_factory=ActorsConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    degrade: DegradeConfig = field(default_factory=DegradeConfig)
    weather: WeatherConfig = field(default_factory=WeatherConfig)
    name: str = field(default="custom", metadata={"internal": True})
    source: str = field(default="", metadata={"internal": True})


VEHICLE_CLASSES = ("car", "truck", "bus", "motorcycle", "construction_vehicle")

# Keys that presets once had, with why they went: refused like any unknown key, with the reason.
REMOVED_KEYS = {
    ("LidarConfig", "fog_background_gain"): "removed: the lidar fog follows the lidar equation with the "
                                            "clear-weather threshold (simgen/degrade.py)",
}


def _check_number(value, typ, meta, where):
    if typ is bool or isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(f"{where}: expected a finite number, got {value!r}")
    if typ is int and not float(value).is_integer():
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    lo, hi = meta.get("lo"), meta.get("hi")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ConfigError(f"{where}: {value!r} is out of range [{lo}, {hi}]")
    return typ(value)


def _build(cls, data: Any, where: str):
    """Build dataclass ``cls`` from a YAML mapping, strictly."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where.rstrip(':')}: expected a mapping, got {type(data).__name__}")
    hints = get_type_hints(cls)
    public = {f.name: f for f in fields(cls) if not f.metadata.get("internal")}
    unknown = sorted(set(data) - set(public))
    for key in unknown:
        if (cls.__name__, key) in REMOVED_KEYS:
            raise ConfigError(f"{where.rstrip(':')}: unknown key {key!r} ({REMOVED_KEYS[cls.__name__, key]})")
    if unknown:
        raise ConfigError(f"{where.rstrip(':')}: unknown key {unknown[0]!r} (allowed: {', '.join(public)})")
    kwargs = {}
    for name, value in data.items():
        f, typ = public[name], hints[name]
        sub = f"{where} {name}" if where.endswith(":") else f"{where}.{name}"
        meta = dict(f.metadata)
        if dataclasses.is_dataclass(typ):
            kwargs[name] = _build(typ, value, sub)
        elif get_origin(typ) is tuple:
            n, et = len(get_args(typ)), get_args(typ)[0]
            if not isinstance(value, (list, tuple)) or len(value) != n:
                raise ConfigError(f"{sub}: expected a list of {n} numbers, got {value!r}")
            kwargs[name] = tuple(_check_number(v, et, meta, sub) for v in value)
            if n == 2 and name != "resolution" and kwargs[name][0] > kwargs[name][1]:
                raise ConfigError(f"{sub}: [min, max] expected, got {value!r}")
        elif typ is dict:
            kwargs[name] = _check_mix(value, sub)
        elif typ is bool:
            if not isinstance(value, bool):
                raise ConfigError(f"{sub}: expected true or false, got {value!r}")
            kwargs[name] = value
        elif typ is str:
            if not isinstance(value, str):
                raise ConfigError(f"{sub}: expected a string, got {value!r}")
            if meta.get("choices") and value not in meta["choices"]:
                raise ConfigError(f"{sub}: {value!r} is not one of {', '.join(meta['choices'])}")
            kwargs[name] = value
        else:
            kwargs[name] = _check_number(value, typ, meta, sub)
    return cls(**kwargs)


def _check_mix(value, where):
    if not isinstance(value, dict) or not value:
        raise ConfigError(f"{where}: expected a mapping of class -> weight")
    for k, v in value.items():
        if k not in VEHICLE_CLASSES:
            raise ConfigError(f"{where}: unknown class {k!r} (allowed: {', '.join(VEHICLE_CLASSES)})")
        _check_number(v, float, {"lo": 0.0, "hi": 1e6}, f"{where}.{k}")
    if sum(value.values()) <= 0:
        raise ConfigError(f"{where}: weights must not all be zero")
    return {k: float(value[k]) for k in VEHICLE_CLASSES if k in value}


def list_presets() -> dict[str, Path]:
    """Preset name -> path, for the YAML files shipped in ``scenes/``."""
    return {p.stem: p for p in sorted(PRESET_DIR.glob("*.yaml"))}


def load_preset(name_or_path: str) -> SceneConfig:
    """Load a preset by name (``urban``) or by path (``my.yaml``), strictly validated."""
    presets = list_presets()
    path = presets.get(name_or_path) or Path(name_or_path)
    if not path.is_file():
        raise ConfigError(f"preset {name_or_path!r}: no such preset or file "
                          f"(presets: {', '.join(presets)})")
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"{path}: not valid YAML{where} ({problem})") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    cfg = _build(SceneConfig, data, f"{path}:")
    check_channels(cfg.degrade.drop_sensors, f"{path}: degrade.drop_sensors")
    check_weather_renderer(cfg, f"{path}: weather.night")
    name = path.stem if name_or_path in presets else str(path)
    return dataclasses.replace(cfg, name=name, source=path.read_text())


def with_degradation(cfg: SceneConfig, **flags) -> SceneConfig:
    """A copy of ``cfg`` whose degrade fields ``flags`` (those not None) replace the preset's,
    each validated like the preset field; errors name the command-line flag."""
    meta = {f.name: f for f in fields(DegradeConfig)}
    hints = get_type_hints(DegradeConfig)
    values = {}
    for name, value in flags.items():
        if value is None:
            continue
        flag = "--" + {"drop_sensors": "drop-sensor"}.get(name, name.replace("_", "-"))
        if name == "drop_sensors":
            check_channels(value, flag)
            values[name] = value
        elif hints[name] is str:
            choices = meta[name].metadata.get("choices")
            if choices and value not in choices:
                raise ConfigError(f"{flag}: {value!r} is not one of {', '.join(choices)}")
            values[name] = value
        else:
            values[name] = _check_number(value, hints[name], dict(meta[name].metadata), flag)
    return dataclasses.replace(cfg, degrade=dataclasses.replace(cfg.degrade, **values))


def with_weather(cfg: SceneConfig, rain: float | None = None, snow: float | None = None,
                 night: bool | None = None) -> SceneConfig:
    """A copy of ``cfg`` whose weather fields given (not None) replace the preset's, each
    validated like the preset field; errors name the command-line flag. Night is refused with
    the Mitsuba renderer, which has no artificial lights or sensor noise model."""
    meta = {f.name: dict(f.metadata) for f in fields(WeatherConfig)}
    values = {name: _check_number(value, float, meta[name], f"--{name}")
              for name, value in (("rain", rain), ("snow", snow)) if value is not None}
    if night is not None:
        values["night"] = bool(night)
    out = dataclasses.replace(cfg, weather=dataclasses.replace(cfg.weather, **values))
    check_weather_renderer(out, "--night")
    return out


def check_weather_renderer(cfg: SceneConfig, where: str) -> None:
    """Night needs the rasteriser's shading (street and vehicle lights, the sensor noise)."""
    if cfg.weather.night and cfg.camera.renderer != "pyrender":
        raise ConfigError(f"{where}: night is rendered by the pyrender camera only, not by "
                          f"{cfg.camera.renderer!r} (use --renderer pyrender)")


def with_renderer(cfg: SceneConfig, renderer: str | None, spp: int | None) -> SceneConfig:
    """A copy of ``cfg`` with another camera renderer and/or samples per pixel."""
    cam = cfg.camera
    if renderer is not None:
        cam = dataclasses.replace(cam, renderer=renderer)
    if spp is not None:
        if not 1 <= spp <= 4096:
            raise ConfigError(f"--spp: {spp} is out of range [1, 4096]")
        cam = dataclasses.replace(cam, spp=spp)
    return dataclasses.replace(cfg, camera=cam)


def with_resolution(cfg: SceneConfig, width: int, height: int) -> SceneConfig:
    """A copy of ``cfg`` with another camera resolution (validated like the preset field)."""
    if not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise ConfigError(f"--resolution: {width}x{height} is out of range [16, 4096] per side")
    return dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, resolution=(width, height)))
