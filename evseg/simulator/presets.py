"""Named scene presets: ``configs/scenes/<name>.yaml`` (installed as ``evseg.configs``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from evseg.errors import ConfigError
from evseg.simulator.scene import SceneConfig, load_scene_file


def _scenes_dir() -> Path:
    return Path(str(resources.files("evseg.configs"))) / "scenes"


def list_scene_presets() -> list[str]:
    """Names of the bundled scene presets, sorted."""
    return sorted(p.stem for p in _scenes_dir().glob("*.yaml"))


def load_scene_preset(name: str) -> SceneConfig:
    """Load a bundled preset by name (e.g. ``"evimo_like"``); ConfigError if unknown."""
    path = _scenes_dir() / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(
            f"unknown scene preset '{name}' (known: {', '.join(list_scene_presets())}; "
            f"or pass a YAML file with --config)"
        )
    return load_scene_file(path)
