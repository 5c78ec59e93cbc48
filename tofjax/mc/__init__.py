"""Monte Carlo photon transport: the reference the analytic model is measured against."""

from .transport import LEDGER as LEDGER
from .transport import MCOptions as MCOptions
from .transport import MCResult as MCResult
from .transport import fresnel_reflectance as fresnel_reflectance
from .transport import photon_mesh as photon_mesh
from .transport import run_mc as run_mc
from .contact import SkinContact as SkinContact
from .slab import SlabOptions as SlabOptions
from .slab import SlabResult as SlabResult
from .slab import run_slab as run_slab
