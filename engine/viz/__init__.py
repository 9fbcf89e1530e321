"""Pictures of a result for people to look at: contact sheets of ground truth | render | error."""

from .contact_sheet import contact_sheet, error_image, write_png

__all__ = ["contact_sheet", "error_image", "write_png"]
