"""The simulator's oracle config (configs/oracle.yaml) for the tests that measure later stages
with perception of known quality: simulated data with gt/, as the default config was before it
became the real path (issue 38). A test that runs the default path says so by not using these."""

from __future__ import annotations

from typing import Any

from configs.schema import ORACLE_CONFIG, Config, load_config

#: on a command line: ``main(["rebuild", *ORACLE_ARGS, ...])``
ORACLE_ARGS = ["--config", str(ORACLE_CONFIG)]


def oracle_config(overrides: dict[str, Any] | None = None) -> Config:
    """configs/oracle.yaml with dotted ``overrides``."""
    return load_config(ORACLE_CONFIG, overrides)


def oracle_yaml(settings: dict[str, Any]) -> dict[str, Any]:
    """A config file's tree that extends configs/oracle.yaml (write it with yaml.safe_dump)."""
    return {"extends": str(ORACLE_CONFIG), **settings}
