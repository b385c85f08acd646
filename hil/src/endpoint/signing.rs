//! MAVLink 2 signing on the vehicle endpoint: the key file (the same format as markhold's
//! `link.signing_key_file`: 32 raw bytes or 64 hex digits), and the verdict on each
//! received frame. Signature arithmetic, timestamps and replay protection are the mavlink
//! crate's (`SigningData`); this only sorts frames into accepted / unsigned / bad.

use std::path::Path;

use mavlink::{MAVLinkV2MessageRaw, SigningConfig, SigningData};

use crate::HilError;
use markhold_config::ConfigError;

/// A 32-byte key from a file: 32 raw bytes, or 64 hex digits (whitespace around them is
/// ignored), like markhold's link.
pub fn read_key(path: &Path) -> Result<[u8; 32], HilError> {
    let bad = |reason: String| {
        let expected = format!("a file of 32 raw bytes or 64 hex digits ({reason})");
        HilError::from(ConfigError::new(
            "endpoint.signing_key_file",
            path.display(),
            expected,
        ))
    };
    let bytes = std::fs::read(path).map_err(|e| bad(e.to_string()))?;
    let mut k = [0u8; 32];
    if bytes.len() == 32 {
        k.copy_from_slice(&bytes);
        return Ok(k);
    }
    let text = String::from_utf8_lossy(&bytes);
    let hex = text.trim();
    if hex.len() == 64 && hex.chars().all(|c| c.is_ascii_hexdigit()) {
        for (i, kb) in k.iter_mut().enumerate() {
            *kb = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).map_err(|e| bad(e.to_string()))?;
        }
        return Ok(k);
    }
    Err(bad(format!("found {} bytes", bytes.len())))
}

/// What signing says about one received frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Verdict {
    /// Signed with our key (or unsigned while unsigned input is accepted).
    Accepted,
    /// MAVLink 1 or unsigned MAVLink 2 while signing is required.
    Unsigned,
    /// Signed, but not with our key, or replayed (timestamp not newer).
    BadSignature,
}

/// The endpoint's signing state: the crate's `SigningData` and one reused frame buffer.
pub(crate) struct Signing {
    data: SigningData,
    accept_unsigned: bool,
    raw: Box<MAVLinkV2MessageRaw>,
}

impl Signing {
    pub(crate) fn new(key: [u8; 32], link_id: u8, accept_unsigned: bool) -> Self {
        Self {
            data: SigningData::from_config(SigningConfig::new(key, link_id, true, accept_unsigned)),
            accept_unsigned,
            raw: Box::new(MAVLinkV2MessageRaw::new()),
        }
    }

    /// For signing what we send.
    pub(crate) fn data(&self) -> &SigningData {
        &self.data
    }

    /// The verdict on one whole, CRC-valid frame (`frame` starts at its magic byte and
    /// ends after its signature, if any).
    pub(crate) fn verify(&mut self, frame: &[u8]) -> Verdict {
        let v2 = frame.first() == Some(&0xFD);
        let signed = v2 && frame.get(2).is_some_and(|f| f & 0x01 != 0);
        if !signed {
            return if self.accept_unsigned {
                Verdict::Accepted
            } else {
                Verdict::Unsigned
            };
        }
        let buf = self.raw.as_mut_slice();
        if frame.len() > buf.len() {
            return Verdict::BadSignature;
        }
        buf[..frame.len()].copy_from_slice(frame);
        if self.data.verify_signature(&self.raw) {
            Verdict::Accepted
        } else {
            Verdict::BadSignature
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{MavMessage, HEARTBEAT_DATA};
    use mavlink::MavHeader;

    fn frame(key: Option<[u8; 32]>) -> Vec<u8> {
        let signer = key.map(|k| SigningData::from_config(SigningConfig::new(k, 0, true, false)));
        let mut out = Vec::new();
        mavlink::write_v2_msg_signed(
            &mut out,
            MavHeader::default(),
            &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()),
            signer.as_ref(),
        )
        .unwrap();
        out
    }

    #[test]
    fn verdicts() {
        let key = [7u8; 32];
        let mut s = Signing::new(key, 0, false);
        assert_eq!(s.verify(&frame(Some(key))), Verdict::Accepted);
        assert_eq!(s.verify(&frame(Some([8u8; 32]))), Verdict::BadSignature);
        assert_eq!(s.verify(&frame(None)), Verdict::Unsigned);
        let f = frame(Some(key));
        assert_eq!(s.verify(&f), Verdict::Accepted);
        // The same frame again is a replay.
        assert_eq!(s.verify(&f), Verdict::BadSignature);
        let mut open = Signing::new(key, 0, true);
        assert_eq!(open.verify(&frame(None)), Verdict::Accepted);
        assert_eq!(open.verify(&frame(Some([8u8; 32]))), Verdict::BadSignature);
    }

    #[test]
    fn key_files() {
        let dir = std::env::temp_dir().join(format!("hil-key-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let raw = dir.join("raw");
        std::fs::write(&raw, [3u8; 32]).unwrap();
        assert_eq!(read_key(&raw).unwrap(), [3u8; 32]);
        let hex = dir.join("hex");
        std::fs::write(&hex, format!("{}\n", "0a".repeat(32))).unwrap();
        assert_eq!(read_key(&hex).unwrap(), [10u8; 32]);
        let short = dir.join("short");
        std::fs::write(&short, b"abc").unwrap();
        let e = read_key(&short).unwrap_err().to_string();
        assert!(
            e.contains("endpoint.signing_key_file") && e.contains("3 bytes"),
            "{e}"
        );
        let e = read_key(&dir.join("missing")).unwrap_err().to_string();
        assert!(e.contains("missing"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
