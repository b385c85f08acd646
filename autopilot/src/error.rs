//! The crate's one error type.

use thiserror::Error;

/// Everything that can go wrong in markhold-autopilot.
#[derive(Debug, Error)]
pub enum AutopilotError {
    /// A configuration key holds a value the code cannot use.
    #[error(transparent)]
    Config(#[from] markhold_config::ConfigError),
    /// The link URL could not be understood.
    #[error("invalid link url `{url}`: {reason}")]
    InvalidUrl {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// Opening the transport (socket, serial port) failed.
    #[error("cannot open {what} `{target}`: {source}")]
    Open {
        /// "udp socket", "tcp connection", "serial port", "runtime".
        what: &'static str,
        /// Address or device.
        target: String,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// Reading the signing key file failed or the file is malformed.
    #[error("signing key file `{path}`: {reason}")]
    SigningKey {
        /// Path of the key file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// The signing timestamp state file beside the key cannot be read, holds no
    /// timestamp, or cannot be written.
    #[error("signing timestamp file `{path}`: {reason}")]
    SigningTimestamp {
        /// Path of the state file.
        path: String,
        /// What is wrong.
        reason: String,
    },
    /// Writing to the transport failed for a reason other than a full buffer.
    #[error("send of {message} failed: {source}")]
    Send {
        /// MAVLink message name.
        message: &'static str,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A command is still waiting for its COMMAND_ACK; one at a time per command id.
    #[error("command {command} already pending")]
    CommandPending {
        /// MAV_CMD number.
        command: u16,
    },
    /// The vehicle rejected or never acknowledged a command.
    #[error("command {command} failed: {reason}")]
    CommandFailed {
        /// MAV_CMD number.
        command: u16,
        /// Result name or "timeout".
        reason: String,
    },
    /// An operation needs a command style the link was not configured for.
    #[error("link configured for `{configured}` commands, `{requested}` requested")]
    WrongCommandMode {
        /// The configured `link.command`.
        configured: &'static str,
        /// What the caller tried to send.
        requested: &'static str,
    },
}
