//! The one error enum of markhold-hil. Each engineer adds the variants of their modules.

#[derive(Debug, thiserror::Error)]
pub enum HilError {
    #[error("{key} = {value}: expected {expected}")]
    InvalidConfig {
        key: String,
        value: String,
        expected: String,
    },
}
