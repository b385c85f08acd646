//! The one error enum of markhold-hil.

#[derive(Debug, thiserror::Error)]
pub enum HilError {
    /// A config key holds a value the simulator cannot use.
    #[error(transparent)]
    Config(#[from] markhold_config::ConfigError),
    /// The camera response named in the site file could not be built.
    #[error("camera response: {source}")]
    CameraResponse {
        #[source]
        source: markhold_exposure::ExposureError,
    },
    /// A socket of the vehicle endpoint or the SITL server could not be opened or used.
    #[error("{what} {addr}: {source}")]
    Socket {
        what: &'static str,
        addr: String,
        #[source]
        source: std::io::Error,
    },
}
