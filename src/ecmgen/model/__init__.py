"""Stage 3, the model: :class:`EcmModel` and its one versioned file, model.json
(:mod:`.model`), the optional effects that ``diagnose`` adds (:mod:`.effects`), and the
discrete 2RC simulation and validation metrics (:mod:`.simulate`, with the shared
recursion in :mod:`.rc`). Everything downstream (C, diagnosis) reads an EcmModel.

The simulator is ``ecmgen.model.simulate.simulate`` (or ``ecmgen.simulate``); it is not
bound here, so that ``ecmgen.model.simulate`` always names the module.
"""

from .effects import EFFECT_NAMES, make_effect
from .model import (DIRECTIONS, RC_FIELDS, EcmModel, InputRecord, OcvTable, RcTable, load_model,
                    model_from_json_dict)
from .simulate import SimResult, Validation, initial_soc, validate

__all__ = ["DIRECTIONS", "EFFECT_NAMES", "RC_FIELDS", "EcmModel", "InputRecord", "OcvTable",
           "RcTable", "SimResult", "Validation", "initial_soc", "load_model", "make_effect",
           "model_from_json_dict", "validate"]
