"""omg: open-vocabulary motion generation on any skeleton, on Lightning."""

__version__ = "0.1.0"
