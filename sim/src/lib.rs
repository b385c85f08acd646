//! The simulation edge (the binary's feature `sim`): the HIL runner, the external-vehicle camera,
//! fault injection, the paper's experiments (`compare`) and their plots, the robustness
//! sweep (`robustness`), the plots of one run (`hil --plots`), and the HIL summary.

pub mod claims;
pub mod cmd;
pub mod compare;
pub mod error;
pub mod external;
pub mod faults;
pub mod hil;
pub mod hold;
pub mod plots;
pub mod robustness;
pub mod robustness_plot;
pub mod run_plots;
pub mod side_by_side;
pub mod sitl_loop;
pub mod stats;
pub mod stream;
pub mod summary;

pub use error::SimError;
