"""Reading mill files and recordings; writing recordings."""
from .millfile import load_mill, parse_mill

__all__ = ["load_mill", "parse_mill"]
