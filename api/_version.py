"""The release number: the one place it is written (pyproject.toml reads it for the package metadata), so
``gravcal --version`` and ``gravcal.__version__`` answer without importlib.metadata (its email parser: ~15 ms)."""
__version__ = "0.1.0"
