"""kinreg's version: the one place it is written (``pyproject.toml`` reads it through hatchling's
``[tool.hatch.version]``). Modules that write it into their outputs import it from here, never
from the package, which would import them back."""

__version__ = "0.1.0"
