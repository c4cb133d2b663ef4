"""The settings of one ``reproduce`` run: what it runs (:class:`Settings`), how it says so, and its
one error."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neural_estimator.paper.reproduce.jobs import EXPERIMENTS
from neural_estimator.paper.reproduce.scales import Scale

INIT_WORDS = {
    "prior": "classical filters start from the scenario prior, the paper's start",
    "truth": "classical filters start at each trajectory's true x0 (mean only), the reading that makes the "
    "paper's PF rows possible",
    "observation": "classical filters start at the state the first observation determines where h is invertible "
    "(mean only; Lorenz 96: x0 = y0), a practitioner's start",
}


class ReproduceError(ValueError):
    """Bad arguments to reproduce (unknown scenario, method or experiment, an --out holding another run)."""


@dataclass
class Settings:
    scale: Scale
    scenarios: list[str]
    methods: list[str]
    gpu: bool
    cache_dir: str
    address: str | None
    num_cpus: int | None
    plugins: tuple[str, ...] = ()  # absolute paths of --plugin files: every Ray worker loads them before its job
    init: str = "prior"  # how the classical filters start in the accuracy and noise experiments (INIT_WORDS)
    experiments: tuple[str, ...] = EXPERIMENTS  # the experiments run (--experiments), in EXPERIMENTS' order

    def to_json(self) -> dict[str, Any]:
        out = {"scale": self.scale.settings(), "scenarios": self.scenarios, "methods": self.methods, "gpu": self.gpu}
        if self.init != "prior":  # the default is left out, so runs from before the option still resume
            out["init"] = self.init
        if tuple(self.experiments) != EXPERIMENTS:  # likewise: every experiment, the default, is left out
            out["experiments"] = list(self.experiments)
        if self.plugins:  # a resumed run must use the same plugin code: its digest is part of the settings
            out["plugins"] = {p: _file_digest(p) for p in self.plugins}
        return out


def _file_digest(path: str) -> str:
    import hashlib

    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except OSError:
        return "missing"


def describe_settings(settings: Settings, n_jobs: int) -> str:
    sc = settings.scale
    lines = [
        f"reproduce --scale {sc.name}: {n_jobs} jobs on Ray "
        f"({settings.address or 'local, ' + str(settings.num_cpus or 'default') + ' CPUs'})",
        f"  scenarios: {', '.join(settings.scenarios)}",
        f"  methods: {', '.join(settings.methods)}",
        f"  experiments: {', '.join(settings.experiments)}",
        f"  init: {settings.init} ({INIT_WORDS[settings.init]})",
    ]
    for k, v in sc.settings().items():
        if k not in ("name", "notes"):
            lines.append(f"  {k}: {'scenario default' if v is None else v}")
    lines += [f"  note: {n}" for n in sc.notes]
    lines.append(f"  runtime on GPU: {'yes' if settings.gpu else 'no (no CUDA device)'}")
    lines.append(f"  result cache: {settings.cache_dir}")
    lines += [f"  plugin: {p}" for p in settings.plugins]
    return "\n".join(lines)
