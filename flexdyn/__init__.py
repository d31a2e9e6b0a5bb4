"""flexdyn: differentiable dynamics of planar chains of rigid and flexible links.

Enables 64-bit floats on import (simulation and identification need double
precision); set `FLEXDYN_NO_X64=1` before importing to leave JAX's setting alone.
"""

import os as _os

import jax as _jax

if not _os.environ.get("FLEXDYN_NO_X64"):
    _jax.config.update("jax_enable_x64", True)

from . import (
    batch as batch,
    control as control,
    denoc as denoc,
    design as design,
    fixed_step as fixed_step,
    fused as fused,
    modes as modes,
    motor as motor,
    nonlinear as nonlinear,
    params as params,
    response as response,
    rigs as rigs,
    scalarize as scalarize,
    shaping as shaping,
    stiffening as stiffening,
    tsit5 as tsit5,
)
from .chain import (
    AssembledChain as AssembledChain,
    Chain as Chain,
    LinkMatrices as LinkMatrices,
    accelerations as accelerations,
    assemble as assemble,
    dissipation as dissipation,
    end_point as end_point,
    input_matrix as input_matrix,
    inverse_dynamics as inverse_dynamics,
    kinetic_energy as kinetic_energy,
    mass_and_velocity_terms as mass_and_velocity_terms,
    mass_matrix as mass_matrix,
    potential_energy as potential_energy,
    root_curvatures as root_curvatures,
    tip_deflections as tip_deflections,
    tip_load as tip_load,
    total_energy as total_energy,
    velocity_terms as velocity_terms,
)
from .fixed_step import rk4_trajectory as rk4_trajectory
from .inputs import (
    AbstractInput as AbstractInput,
    BangBang as BangBang,
    FunctionInput as FunctionInput,
    PDTracking as PDTracking,
    QuinticReference as QuinticReference,
    SampledTorque as SampledTorque,
    ZeroTorque as ZeroTorque,
)
from .lagged_input import LaggedTorque as LaggedTorque
from .linear import (
    LinearModel as LinearModel,
    Modes as Modes,
    damped_modes as damped_modes,
    linearize as linearize,
    modal_analysis as modal_analysis,
    modal_configuration as modal_configuration,
    natural_frequencies as natural_frequencies,
    stable_step as stable_step,
    stiffness_matrix as stiffness_matrix,
)
from .motor import DCMotor as DCMotor
from .parts import (
    ElasticJoint as ElasticJoint,
    FlexibleLink as FlexibleLink,
    Hub as Hub,
    Payload as Payload,
    RigidJoint as RigidJoint,
    RigidLink as RigidLink,
)
from .program_cache import (
    MappingLimitWarning as MappingLimitWarning,
    ensure_mapping_headroom as ensure_mapping_headroom,
    mapping_count as mapping_count,
    mapping_limit as mapping_limit,
)
from .sampled_loop import (
    ClosedLoopRun as ClosedLoopRun,
    DigitalController as DigitalController,
    LinearFeedback as LinearFeedback,
    simulate_closed_loop as simulate_closed_loop,
)
from .simulation import (
    ChainVectorField as ChainVectorField,
    Outputs as Outputs,
    Trajectory as Trajectory,
    initial_state as initial_state,
    observe as observe,
    simulate as simulate,
)
from .solvers import RK4 as RK4
from .stiffening import FirstModeStiffening as FirstModeStiffening, first_mode_stiffening as first_mode_stiffening
from .tsit5 import tsit5_trajectory as tsit5_trajectory

__version__ = "0.1.0"
from .params import (
    UnknownParameterError as UnknownParameterError,
    get_parameter as get_parameter,
    is_signed as is_signed,
    parameter_names as parameter_names,
    parameter_unit as parameter_unit,
    with_optional_terms as with_optional_terms,
    with_parameters as with_parameters,
)
