"""The settings of a `simgen make` run and the per-scene random streams (light: no rendering
or ray-casting imports, so the process that only coordinates workers stays small)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .config import SceneConfig


@dataclass(frozen=True)
class MakeSettings:
    """Everything that determines the bytes of a dataset."""
    cfg: SceneConfig
    n_scenes: int
    seed: int
    samples_per_scene: int
    version: str
    val_fraction: float = 0.2
    gl: str | None = None
    dense_labels: bool = False     # a depth and a class image beside each camera image

    def fingerprint(self) -> dict:
        """The settings a resumed run must share with the parts already written. Dense labels
        and the weather enter it only when on, so a set made without them keeps the fingerprint
        (and the settings file) that it had before the options existed."""
        d = dataclasses.asdict(self.cfg)
        d.pop("source")
        if not self.cfg.weather.active:    # likewise the weather: a clear-day set keeps its fingerprint
            d.pop("weather")
        fp = {"cfg": d, "seed": self.seed, "samples_per_scene": self.samples_per_scene,
              "version": self.version, "val_fraction": self.val_fraction}
        if self.dense_labels:
            fp["dense_labels"] = True
        return fp


def scene_rng(seed: int, idx: int, stream: int) -> np.random.Generator:
    """Independent generators per (seed, scene, stream): 0 = world, 1 = sensors, 2 = degradation,
    3 = occluders, 4-8 = the weather (:class:`WeatherStreams`), 100 + camera index = that
    camera's lens dirt."""
    return np.random.default_rng(np.random.SeedSequence([seed, idx, stream]))


def degradation_stream(s: MakeSettings, idx: int) -> tuple[np.ndarray, np.random.Generator]:
    """Scene ``idx``'s degradation stream (2) and its first draw: the dropped lidar rings, (k,)
    int, empty without beam drop. The rings are drawn first, so they are known without making
    the scene (the dataset's degradation record lists them for every scene, also for those made
    by an earlier, interrupted run); the fog draws from the generator after them."""
    from .degrade import choose_rings
    rng = scene_rng(s.seed, idx, 2)
    n_drop = s.cfg.degrade.beam_drop
    rings = choose_rings(n_drop, rng) if n_drop else np.zeros(0, int)
    return rings, rng


@dataclass
class WeatherStreams:
    """A scene's weather generators, one per model and sensor, so that turning one model on
    changes no draw of another (nor of the world, the clean sensors or the degradation)."""
    rain_lidar: np.random.Generator
    snow_lidar: np.random.Generator
    rain_camera: np.random.Generator
    snow_camera: np.random.Generator
    night_camera: np.random.Generator


def weather_streams(s: MakeSettings, idx: int) -> WeatherStreams:
    """Scene ``idx``'s weather streams 4-8."""
    return WeatherStreams(*(scene_rng(s.seed, idx, stream) for stream in range(4, 9)))
