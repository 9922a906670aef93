"""config/silo-agent.example.toml says it shows every key: every field of the config models
appears in it (set, or commented out with an example value), and it names no key they lack."""

from __future__ import annotations

import re
import typing
from pathlib import Path

from pydantic import BaseModel

from silo_agent.config import Config

EXAMPLE = Path(__file__).parents[1] / "config" / "silo-agent.example.toml"


def model_of(annotation: object) -> type[BaseModel] | None:
    """The pydantic model a field holds (itself, in a list, or optional), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = model_of(arg)
        if found is not None:
            return found
    return None


def model_keys(model: type[BaseModel], prefix: str = "") -> set[str]:
    """Dotted keys of every leaf field: `mqtt.tls.ca_file`, `cameras.serial`."""
    keys: set[str] = set()
    for name, field in model.model_fields.items():
        sub = model_of(field.annotation)
        keys |= {f"{prefix}{name}"} if sub is None else model_keys(sub, f"{prefix}{name}.")
    return keys


def example_keys(text: str) -> set[str]:
    """Dotted keys the example shows: `key = ...` lines, commented out or not, under their
    `[section]` or `[[array]]` header."""
    section, keys = "", set()
    for line in text.splitlines():
        header = re.match(r"^#?\s*\[\[?([a-z_.]+)\]\]?", line)
        if header:
            section = header.group(1) + "."
            continue
        key = re.match(r"^#?\s?([a-z_0-9]+)\s*=", line)
        if key:
            keys.add(section + key.group(1))
    return keys


def test_the_example_shows_every_key_of_the_config_models() -> None:
    shown = example_keys(EXAMPLE.read_text(encoding="utf-8"))
    fields = model_keys(Config)
    assert sorted(fields - shown) == [], "keys missing from the example"
    assert sorted(shown - fields) == [], "keys in the example that the config does not have"


def test_the_key_reader_sees_sections_and_commented_keys() -> None:
    text = '[silo]\nid = "a"\n# ceiling_z = 1.5   # optional\n[[cameras]]\nserial = "x"\n'
    assert example_keys(text) == {"silo.id", "silo.ceiling_z", "cameras.serial"}
    assert {"live.rate_hz", "mqtt.tls.ca_file", "cameras.serial"} <= model_keys(Config)
