"""A seedable numpy Generator whose exact state round-trips through JSON."""

from __future__ import annotations

from typing import Any

import numpy as np


def make_rng(seed: int | None) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(seed))


def _stringify(value: Any) -> Any:
    # 128-bit PCG64 integers exceed what many JSON consumers keep exactly: store as text.
    if isinstance(value, dict):
        return {k: _stringify(v) for k, v in value.items()}
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return value


def _unstringify(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _unstringify(v) for k, v in value.items()}
    if isinstance(value, str) and value.lstrip("-").isdigit():
        return int(value)
    return value


def rng_state(rng: np.random.Generator) -> dict[str, Any]:
    state = dict(rng.bit_generator.state)
    name = state.pop("bit_generator")
    return {"bit_generator": name, **_stringify(state)}


#: seeds the generator that a stored state then overwrites (drawing OS entropy for it costs 3× more)
_PLACEHOLDER_SEED = np.random.SeedSequence(0)


def rng_from_state(state: dict[str, Any]) -> np.random.Generator:
    state = dict(state)
    name = state.pop("bit_generator")
    if name != "PCG64":
        raise ValueError(f"unsupported bit generator {name!r}")
    bg = np.random.PCG64(_PLACEHOLDER_SEED)
    bg.state = {"bit_generator": name, **_unstringify(state)}  # type: ignore[typeddict-item]  # keys come from the state
    return np.random.Generator(bg)
