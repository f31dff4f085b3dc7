"""Command-line overrides as Hydra reads them: a value quoted for its grammar, and every Lightning Trainer argument
settable as ``trainer.<arg>=...``."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from omegaconf import OmegaConf

from nvs.run.component_schema import RESERVED, component_schema
from nvs.run.compose import CONF_DIR


def hydra_value(value: str) -> str:
    """``value`` written for the right-hand side of a Hydra override: as is where Hydra's grammar reads it back
    unchanged, else single-quoted (a path with spaces, non-ASCII letters or quotes: the bare form fails to parse)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    try:
        if parser.parse_overrides([f"k={value}"])[0].value() == value:
            return value
    except HydraException:
        pass
    # Inside quotes a run of backslashes is literal unless it precedes a quote: there each one is doubled.
    body = re.sub(r"(\\*)'", lambda m: m[1] * 2 + "\\'", value)
    body = re.sub(r"(\\+)$", lambda m: m[1] * 2, body)
    return f"'{body}'"


def trainer_arguments(argv: Sequence[str], conf_dir: str | Path = CONF_DIR) -> list[str]:
    """Command-line arguments with ``trainer.<arg>=v`` for an argument of conf/trainer's ``_target_`` (Lightning's
    Trainer) that the file does not list rewritten to ``++trainer.<arg>=v``, so every Trainer argument is set without
    '+'. Any other ``trainer.<key>=v`` is left to fail composing, as an unknown key (``nvs.train.check_composes``)."""
    trainer = OmegaConf.load(Path(conf_dir) / "trainer" / "default.yaml")
    asked = {arg.split("=", 1)[0].removeprefix("trainer.") for arg in argv if arg.startswith("trainer.")}
    if not asked - set(trainer):
        return list(argv)  # nothing to rewrite: the Trainer's signature (importing Lightning, seconds) is not read
    schema = component_schema(str(trainer.get("_target_", "lightning.pytorch.Trainer")))
    known = set(schema.names) - set(trainer) - set(RESERVED) if schema else set()
    return [f"++{arg}" if arg.split("=", 1)[0].removeprefix("trainer.") in known and arg.startswith("trainer.")
            else arg for arg in argv]
