//! The one error enum of markhold-hil. Each module adds its own variants.

#[derive(Debug, thiserror::Error)]
pub enum HilError {
    #[error("{key} = {value}: expected {expected}")]
    InvalidConfig {
        key: String,
        value: String,
        expected: String,
    },
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
