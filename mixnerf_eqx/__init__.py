"""MixNeRF (CVPR 2023) on JAX and Equinox: few-shot novel view synthesis with mixture densities.

The top level holds what most scripts need (`load_config`, `fit`, `evaluate`, `render_views`,
`predictive`, ...; `__init__.pyi` lists them); the rest is in namespaces that follow the
package's layers: `mx.nn` (the model), `mx.training`, `mx.inference`, `mx.uncertainty`,
`mx.runs`, `mx.data`, `mx.metrics`, `mx.config` and `mx.runtime`. Names load on first use, so
`import mixnerf_eqx` is quick and changes nothing in the process: the commands set up their
allocator and Ctrl-C handling themselves (`mixnerf_eqx._util.entry`), `fit` its own.

The package's modules are imported through jaxtyping's import hook with beartype, so every
annotated function and Module checks the shapes and dtypes of its arguments while JAX traces
(a compiled step pays nothing). `mx.set_typecheck(False)`, `--no-typecheck` or
`JAXTYPING_DISABLE=1` turn the checks off: see `mixnerf_eqx._util.typecheck`.
"""

import warnings as _warnings

import jaxtyping as _jaxtyping
import lazy_loader as _lazy_loader

# The commands' start-up modules and the table of moved names use the standard library only;
# loaded before the hook, they stay unchecked, so that a command restarts itself with its
# allocator before anything imports JAX (which the hook's checks do).
from ._util import allocator as _allocator  # noqa: F401
from ._util import entry as _entry  # noqa: F401
from ._util import interrupt as _interrupt  # noqa: F401
from ._util.moved import moved_name as _moved_name

# The hook stays for the package's other modules, which load as they are used.
_jaxtyping.install_import_hook(__name__, "beartype.beartype")

_load, __dir__, __all__ = _lazy_loader.attach_stub(__name__, __file__)


def __getattr__(name: str):
    try:
        return _load(name)
    except AttributeError:
        place, value = _moved_name(name)  # a name of an earlier release, or AttributeError
        _warnings.warn(
            f"mixnerf_eqx.{name} is deprecated and will be removed in the next release: use {place}",
            DeprecationWarning,
            stacklevel=2,
        )
        globals()[name] = value  # warned once: `from mixnerf_eqx import name` looks twice
        return value
