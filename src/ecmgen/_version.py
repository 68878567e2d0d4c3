"""The package version, in one place: ``ecmgen.__version__`` re-exports it, and the
modules that stamp it into their outputs (model.json, the C banner, ``--version``)
import it from here rather than from the package facade."""

__version__ = "0.1.0"
