"""LLFF dataparser (``ns-train <method> llff --data DIR``). Work in progress."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig
from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from virgi_ns import compat  # noqa: F401  (checkpoint-loading work-arounds for torch >= 2.6)


@dataclass
class LLFFDataParserConfig(DataParserConfig):
    """LLFF scenes: ``poses_bounds.npy`` beside an image folder."""

    _target: Type = field(default_factory=lambda: LLFF)


class LLFF(DataParser):
    """Reads an LLFF capture."""

    config: LLFFDataParserConfig


llff_dataparser = DataParserSpecification(config=LLFFDataParserConfig(), description="LLFF poses_bounds.npy scenes")
