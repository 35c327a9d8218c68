"""Optimisers built without importing TorchDynamo, which costs 1.5 CPU-seconds a process.

``torch.optim.Optimizer``'s ``add_param_group``, ``state_dict``, ``load_state_dict`` and
``zero_grad`` carry ``torch._disable_dynamo``: on its first call each imports ``torch._dynamo``
(``torch.compile``'s tracer) to build a version that compiled code will not trace into. No
training process here compiles anything, yet every one paid that import building its optimiser:
1.5 of the 5.7 CPU-seconds a process took to start (issue 66), which a table's ten short runs, the
test suite's hundreds of processes and every evaluation pay again.

:func:`defer_dynamo_import` gives each of those methods a stand-in for the disabled version
that calls the method itself while ``torch._dynamo`` has not been imported, which is exactly what
the disabled version does then: until TorchDynamo is imported, no frame can be being compiled.
Once anything imports it, the next call builds PyTorch's own disabled version and keeps it, so
compiled code is treated as PyTorch intends.

It leans on how ``torch._compile._disable_dynamo`` caches its wrapper (an attribute
``__dynamo_disable`` on the wrapped function), checked when it is applied: where a PyTorch
release does it otherwise, nothing is changed and the import is merely paid.
"""

from __future__ import annotations

import functools
import inspect
import sys
from collections.abc import Callable
from typing import Any

import torch

# torch._compile._disable_dynamo keeps the disabled version on the wrapped function under
# this name, and calls it if present (torch 2.13).
_CACHE_ATTRIBUTE = "__dynamo_disable"
_WRAPPED_METHODS = ("add_param_group", "state_dict", "load_state_dict", "zero_grad")


def _deferred(method: Callable[..., Any]) -> Callable[..., Any]:
    """``method`` itself while TorchDynamo is not imported; PyTorch's disabled version of it
    (built once, then cached as PyTorch caches it) from the first call after."""

    @functools.wraps(method)
    def call(*args: Any, **kwargs: Any) -> Any:
        if "torch._dynamo" not in sys.modules:
            return method(*args, **kwargs)
        import torch._dynamo

        disabled = torch._dynamo.disable(method, recursive=True, wrapping=False)
        setattr(method, _CACHE_ATTRIBUTE, disabled)
        return disabled(*args, **kwargs)

    call.deferred_dynamo = True  # type: ignore[attr-defined]
    return call


def _caches_on_the_function() -> bool:
    """Whether this PyTorch's ``_disable_dynamo`` reads its cache from the attribute."""
    try:
        source = inspect.getsource(torch._compile._disable_dynamo)
    except (OSError, TypeError, AttributeError):
        return False
    return f'getattr(fn, "{_CACHE_ATTRIBUTE}", None)' in source


def defer_dynamo_import() -> bool:
    """Let optimisers be built and used without importing TorchDynamo (the module's
    docstring). Idempotent; returns whether the stand-ins are in place."""
    if not _caches_on_the_function():
        return False
    for name in _WRAPPED_METHODS:
        method = getattr(torch.optim.Optimizer.__dict__.get(name), "__wrapped__", None)
        if method is None:
            return False
        if getattr(method, _CACHE_ATTRIBUTE, None) is None:
            setattr(method, _CACHE_ATTRIBUTE, _deferred(method))
    return True
