"""The skin contact model lives in :mod:`tofjax.model.contact` (the analytic model's guided optics
uses it too, and the model never imports the Monte Carlo); re-exported here for the Monte Carlo."""

from ..model.contact import SkinContact as SkinContact
from ..model.contact import diffuse_reflectance_semi_infinite as diffuse_reflectance_semi_infinite

__all__ = ["SkinContact", "diffuse_reflectance_semi_infinite"]
