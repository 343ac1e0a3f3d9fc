"""The project's version, in a module of its own so that code of the ``sim`` package can read it without
importing the package's face (which would close an import cycle)."""

__version__ = "0.1.0"
