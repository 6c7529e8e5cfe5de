"""The strict base of every config model, and one way to turn user config (None, a mapping, an OmegaConf node or the model itself) into a
validated pydantic model, with an error that names every offending field (docs/style.md rule 6)."""

from __future__ import annotations

from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from uavlae.errors import ConfigError

M = TypeVar("M", bound=BaseModel)
# fields whose value an error never quotes: a key typed in the wrong place must not reach a log
UNQUOTED_FIELDS = ("api_key_env", "api_key", "key", "token", "secret", "password")


class StrictModel(BaseModel):
    """The base of every config model: unknown keys, NaN/inf and wrong types are errors, and a
    validated config is immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, validate_default=True)


def config_data(cfg: Any) -> dict[str, Any]:
    """User config as a plain dict: None is empty, a model is dumped, an OmegaConf node is resolved."""
    if cfg is None:
        return {}
    if isinstance(cfg, BaseModel):
        return cfg.model_dump()
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            cfg = OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)


def parse_model(model: type[M], cfg: Any, *, prefix: str, title: str, **overrides: Any) -> M:
    """Validate ``cfg`` (plus ``overrides``) into ``model``.

    Raises :class:`~uavlae.errors.ConfigError` (a ``ValueError``), ``"invalid <title> config: ..."``
    with one line per error, each naming the field as ``<prefix>.<path>`` and the value it got;
    nothing half-built is returned.
    """
    if isinstance(cfg, model) and not overrides:
        return cfg
    data = config_data(cfg)
    data.update(overrides)
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ConfigError(f"invalid {title} config:\n  " + "\n  ".join(error_lines(e, prefix))) from None


def error_lines(e: ValidationError, prefix: str) -> list[str]:
    """One line per error, naming the field and the value it got; an unknown key's value is not
    quoted (its name is what is wrong, and a value typed under a wrong name may be a secret), nor
    is a whole section's (a rule between two keys names both with their values, and the section
    holds every other key as well)."""
    lines = []
    for err in e.errors():
        field = f"{prefix}.{'.'.join(str(p) for p in err['loc'])}" if err["loc"] else prefix
        quiet = (err["type"] == "extra_forbidden" or isinstance(err.get("input"), dict)
                 or (err["loc"] and str(err["loc"][-1]) in UNQUOTED_FIELDS))
        got = "" if quiet else f" (got {err.get('input')!r})"
        lines.append(f"{field}: {err['msg'].removeprefix('Value error, ')}{got}")
    return lines
