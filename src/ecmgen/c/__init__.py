"""Stage 4a, model -> C for BMS microcontrollers (float32 or fixed point).

:mod:`.qformat` the Q-format arithmetic, :mod:`.spec` (float32) and :mod:`.qspec` (fixed
point) the spec of every number the C holds, :mod:`.codegen` its rendering through
``templates/`` with the runtime of ``c_runtime/``,
:mod:`.cref` the float32 and bit-true integer Python references, :mod:`.cbuild` the host
build (cffi) and the C-vs-Python equivalence, :mod:`.check` the C stage of
``ecmgen build`` (generate, then check), :mod:`.target` Cortex-M cross builds and QEMU.
The compiler toolchains and cffi are used only when something is built.
"""

from .cbuild import CBuildError, c_equivalence
from .check import build_c_outputs
from .codegen import C_EFFECTS, NUMERICS, CSpec, file_names, generate_c, prepare, render

__all__ = ["C_EFFECTS", "NUMERICS", "CBuildError", "CSpec", "build_c_outputs", "c_equivalence",
           "file_names", "generate_c", "prepare", "render"]
