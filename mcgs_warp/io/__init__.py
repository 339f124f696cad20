"""Reading and writing files: atomic writes, images, and (later) USD/PLY maps."""

from .atomic import atomic_write, read_image, write_image

__all__ = ["atomic_write", "read_image", "write_image"]
