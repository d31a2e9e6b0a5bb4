"""flexdyn: differentiable dynamics of planar chains of rigid and flexible links.

Enables 64-bit floats on import (simulation and identification need double
precision); set `FLEXDYN_NO_X64=1` before importing to leave JAX's setting alone.
"""

import os as _os

import jax as _jax

if not _os.environ.get("FLEXDYN_NO_X64"):
    _jax.config.update("jax_enable_x64", True)

from . import modes as modes
from . import rigs as rigs
from .chain import (
    AssembledChain as AssembledChain,
)
from .chain import (
    Chain as Chain,
)
from .chain import (
    LinkMatrices as LinkMatrices,
)
from .chain import (
    accelerations as accelerations,
)
from .chain import (
    assemble as assemble,
)
from .chain import (
    dissipation as dissipation,
)
from .chain import (
    end_point as end_point,
)
from .chain import (
    input_matrix as input_matrix,
)
from .chain import (
    inverse_dynamics as inverse_dynamics,
)
from .chain import (
    kinetic_energy as kinetic_energy,
)
from .chain import (
    mass_and_velocity_terms as mass_and_velocity_terms,
)
from .chain import (
    mass_matrix as mass_matrix,
)
from .chain import (
    potential_energy as potential_energy,
)
from .chain import (
    root_curvatures as root_curvatures,
)
from .chain import (
    tip_deflections as tip_deflections,
)
from .chain import (
    tip_load as tip_load,
)
from .chain import (
    total_energy as total_energy,
)
from .chain import (
    velocity_terms as velocity_terms,
)
from .inputs import (
    AbstractInput as AbstractInput,
)
from .inputs import (
    BangBang as BangBang,
)
from .inputs import (
    FunctionInput as FunctionInput,
)
from .inputs import (
    PDTracking as PDTracking,
)
from .inputs import (
    QuinticReference as QuinticReference,
)
from .inputs import (
    SampledTorque as SampledTorque,
)
from .inputs import (
    ZeroTorque as ZeroTorque,
)
from .linear import (
    LinearModel as LinearModel,
)
from .linear import (
    Modes as Modes,
)
from .linear import (
    damped_modes as damped_modes,
)
from .linear import (
    linearize as linearize,
)
from .linear import (
    modal_analysis as modal_analysis,
)
from .linear import (
    stiffness_matrix as stiffness_matrix,
)
from .parts import (
    ElasticJoint as ElasticJoint,
)
from .parts import (
    FlexibleLink as FlexibleLink,
)
from .parts import (
    Hub as Hub,
)
from .parts import (
    Payload as Payload,
)
from .parts import (
    RigidJoint as RigidJoint,
)
from .parts import (
    RigidLink as RigidLink,
)
from .simulate import (
    ChainVectorField as ChainVectorField,
)
from .simulate import (
    Outputs as Outputs,
)
from .simulate import (
    Trajectory as Trajectory,
)
from .simulate import (
    initial_state as initial_state,
)
from .simulate import (
    observe as observe,
)
from .simulate import (
    simulate as simulate,
)
from .solvers import RK4 as RK4

__version__ = "0.1.0"
from .params import (
    get_parameter as get_parameter,
)
from .params import (
    is_signed as is_signed,
)
from .params import (
    parameter_names as parameter_names,
)
from .params import (
    parameter_unit as parameter_unit,
)
from .params import (
    with_parameters as with_parameters,
)
