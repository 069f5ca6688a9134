"""The one Warp module that every kernel and function of the solver is built in.

Warp compiles, caches and loads code per Warp module, by default one a Python module. The
solver's kernels are split into files by stage, but stay one Warp module, named after this
package as when they were one file: one build, one cache entry and one load on a device, as
before. Every decorator in this package names :data:`MODULE`: ``@wp.kernel(module=MODULE)``,
``@wp.func(module=MODULE)``, ``@_module.func_native(...)`` (:func:`func_native` below) and
``wp.Kernel(..., module=MODULE)``.
"""

from __future__ import annotations

import warp as wp

from ... import _warp  # noqa: F401  (Warp's log level: no start-up banner in logs and CLI output)

#: the Warp module's name: the package's (``knockgs_core.sim._kernels``)
NAME = __name__.rpartition(".")[0]
#: the Warp module of every kernel and function of the package
MODULE = wp.get_module(NAME)
wp.set_module_options({"enable_backward": False}, module=MODULE)

#: cap on the registers per thread of the GPU's heavy particle kernels (G2P and the fused G2P;
#: CUDA ``__maxnreg__``, ignored on the CPU): more threads resident per SM to hide their memory
#: latency, at the cost of a few spills. The caps tried and their substep times are in
#: benchmarks/results/2026-11-27-layout-and-instructions.md
CUDA_MAX_REGISTERS = 80


def func_native(snippet: str):
    """``wp.func_native(snippet)`` registering into :data:`MODULE`. Warp 1.19's ``func_native``
    takes no module argument and registers a function in the Warp module named by its
    ``__module__``, so the stub is given the package's name first. Decorate as
    ``@_module.func_native(...)``: Warp tells a native function by its decorator's form, an
    attribute named ``func_native`` (a bare name would lose the stub's return type)."""

    def register(f):
        f.__module__ = NAME
        return wp.func_native(snippet)(f)

    return register
