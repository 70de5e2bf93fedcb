"""Method specifications registered with nerfstudio (``ns-train virgi``, ``ns-train virgi-vanilla``).

Placeholder until the VIRGi model lands (issue 4): both entries point at splatfacto's recipe
under our names, so nerfstudio's method discovery works with this package installed.
"""

from __future__ import annotations

import copy

from nerfstudio.configs.method_configs import method_configs
from nerfstudio.plugins.types import MethodSpecification

from virgi_ns import compat  # noqa: F401  (checkpoint-loading work-arounds for torch >= 2.6)


def _placeholder(name: str) -> MethodSpecification:
    cfg = copy.deepcopy(method_configs["splatfacto"])
    cfg.method_name = name
    return MethodSpecification(config=cfg, description=f"{name} (placeholder: splatfacto recipe)")


virgi_method = _placeholder("virgi")
virgi_vanilla_method = _placeholder("virgi-vanilla")
