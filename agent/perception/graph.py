"""A perception network run as a frozen TorchScript graph, when that changes nothing.

``FrozenNet(module, precision)`` is called like the module. The first call traces a copy
(in bf16 when ``precision`` is "bf16", the weights cast once instead of at every layer as
autocast does) and freezes it: oneDNN fuses each convolution with its ReLU and prepacks the
weights, and no Python runs per layer. On that first input it runs the eager module too
(under bf16 autocast when asked) and keeps the graph only when every output is bit for bit
the same; otherwise, or when tracing fails, it runs the eager module from then on
(``tidee bench agent`` times the agent's whole step).

The graph is built in the process that runs it: a copy or a pickle of a ``FrozenNet`` carries
the module alone and traces again on its first call.
"""

from __future__ import annotations

import copy
import logging
import warnings
from typing import Any

import torch
from torch import nn

log = logging.getLogger(__name__)


class FrozenNet:
    def __init__(self, module: nn.Module, precision: str) -> None:
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be fp32 or bf16, not {precision!r}")
        self.module = module.eval()
        self.precision = precision
        self._graph: Any = None  # None: not built yet; False: the eager module is used
        self.frozen: bool | None = None  # after the first call: whether the graph runs

    def __call__(self, *inputs: torch.Tensor) -> Any:
        if self._graph is None:
            self._graph = self._build(inputs)
            self.frozen = self._graph is not False
        if self._graph is False:
            return self._eager(*inputs)
        with torch.inference_mode():
            return self._graph(*self._cast(inputs))

    def _eager(self, *inputs: torch.Tensor) -> Any:
        bf16 = self.precision == "bf16"
        with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            return self.module(*inputs)

    def _cast(self, inputs: tuple[torch.Tensor, ...]) -> list[torch.Tensor]:
        if self.precision != "bf16":
            return list(inputs)
        return [x.to(torch.bfloat16) if x.is_floating_point() else x for x in inputs]

    def _build(self, inputs: tuple[torch.Tensor, ...]) -> Any:
        try:
            net = copy.deepcopy(self.module)
            if self.precision == "bf16":
                net = net.to(torch.bfloat16)
            with torch.inference_mode(), warnings.catch_warnings():
                warnings.simplefilter("ignore")  # TracerWarnings: shape checks traced as constants
                graph = torch.jit.freeze(torch.jit.trace(net, tuple(self._cast(inputs)), strict=False))
                got = graph(*self._cast(inputs))
        except Exception as e:  # an operator TorchScript cannot trace: the eager module serves
            log.info("%s: running eagerly (tracing failed: %s)", type(self.module).__name__, e)
            return False
        if not _same(got, self._eager(*inputs)):
            log.info("%s: running eagerly (the frozen graph's outputs differ)", type(self.module).__name__)
            return False
        return graph

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_graph": None, "frozen": None}

    def __deepcopy__(self, memo: dict[int, Any]) -> FrozenNet:
        return FrozenNet(copy.deepcopy(self.module, memo), self.precision)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    return False
