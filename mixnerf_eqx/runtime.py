"""How the process runs (re-exports only): the memory allocator of the commands, JAX's
persistent compilation cache, and the switch for runtime shape checks.

    import mixnerf_eqx as mx
    mx.runtime.set_typecheck(False)          # or mx.set_typecheck
    mx.runtime.enable_compilation_cache()
"""

from ._util.allocator import allocator_in_use as allocator_in_use
from ._util.allocator import allocator_library as allocator_library
from ._util.allocator import preload_allocator as preload_allocator
from ._util.compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._util.typecheck import set_typecheck as set_typecheck
from ._util.typecheck import typecheck_enabled as typecheck_enabled
