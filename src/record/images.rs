//! The camera images of a recording, frame by frame, for the commands that only need the
//! pixels (`markhold map`): read record by record like replay (memory does not grow with
//! the file), no loop rebuilt.

use std::collections::HashMap;
use std::path::Path;

use anyhow::Context as _;
use foxglove::schemas::CompressedImage;
use foxglove::Decode;
use markhold_exposure::{Frame, FrameMeta};

use super::replay::{decode_image, lengths_fit, run_info_of, MAX_RECORD_BYTES};
use super::{METADATA_NAME, TOPIC_IMAGE};

/// What [`for_each_image`] read.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImagesRead {
    /// Images in the recording, and those handed on (every `every`th).
    pub images: u64,
    pub handed: u64,
    /// Lossy (JPEG) images among those handed on.
    pub lossy: u64,
    /// The file ended early (truncated or never finalized): why; what was read is what
    /// its complete chunks held.
    pub ended_early: Option<String>,
}

/// Decode every `every`th camera image of the recording `path` into a frame of the
/// recorded camera's size and hand it to `f` (frame meta: the image's index as `seq`,
/// its log time as the stamp). The recording's metadata gives the image size; a file
/// that is not a markhold recording is an error naming it.
pub fn for_each_image(
    path: &Path,
    every: u64,
    mut f: impl FnMut(&Frame) -> anyhow::Result<()>,
) -> anyhow::Result<ImagesRead> {
    use mcap::records::Record;
    use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};

    let file = crate::params::open_regular(path, u64::MAX)
        .with_context(|| format!("reading {}", path.display()))?;
    let mut src = std::io::BufReader::with_capacity(1 << 20, file);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(MAX_RECORD_BYTES),
    );
    let every = every.max(1);
    let mut image_channels: HashMap<u16, bool> = HashMap::new();
    let mut frame: Option<Frame> = None;
    let mut out = ImagesRead::default();
    while let Some(event) = reader.next_event() {
        let (opcode, data) = match event {
            Ok(LinearReadEvent::ReadRequest(n)) => {
                let got = std::io::Read::read(&mut src, reader.insert(n.min(MAX_RECORD_BYTES)))
                    .with_context(|| format!("reading {}", path.display()))?;
                reader.notify_read(got);
                continue;
            }
            Ok(LinearReadEvent::Record { opcode, data }) => (opcode, data),
            Err(e) => {
                out.ended_early = Some(e.to_string());
                break;
            }
        };
        if !matches!(
            opcode,
            mcap::records::op::CHANNEL | mcap::records::op::METADATA | mcap::records::op::MESSAGE
        ) {
            continue;
        }
        if !lengths_fit(opcode, data) {
            out.ended_early = Some(format!(
                "a record (opcode {opcode:#04x}) declares a string longer than itself"
            ));
            break;
        }
        let record = match mcap::parse_record(opcode, data) {
            Ok(r) => r,
            Err(e) => {
                out.ended_early = Some(e.to_string());
                break;
            }
        };
        match record {
            Record::Channel(c) => {
                image_channels.insert(c.id, c.topic == TOPIC_IMAGE);
            }
            Record::Metadata(m) if m.name == METADATA_NAME && frame.is_none() => {
                let (_, site) = run_info_of(path, &m.metadata)?;
                frame = Some(Frame::new(site.calibration.width, site.calibration.height));
            }
            Record::Message { header, data } => {
                if !image_channels
                    .get(&header.channel_id)
                    .copied()
                    .unwrap_or(false)
                {
                    continue;
                }
                let Some(frame) = frame.as_mut() else {
                    anyhow::bail!(
                        "{}: an image before the `{METADATA_NAME}` metadata: not a markhold recording",
                        path.display()
                    );
                };
                let index = out.images;
                out.images += 1;
                if !index.is_multiple_of(every) {
                    continue;
                }
                let img = CompressedImage::decode(&*data)
                    .map_err(|e| anyhow::anyhow!("{}: image {index}: {e}", path.display()))?;
                match img.format.as_str() {
                    "png" => {}
                    "jpeg" => out.lossy += 1,
                    other => anyhow::bail!(
                        "{}: image {index}: format {other:?}: expected png or jpeg",
                        path.display()
                    ),
                }
                decode_image(&img.data, frame)
                    .with_context(|| format!("{}: image {index}", path.display()))?;
                frame.meta = FrameMeta {
                    seq: index,
                    stamp_s: header.log_time as f64 * 1e-9,
                    exposure_us: 0.0,
                    gain_db: 0.0,
                };
                out.handed += 1;
                f(frame)?;
            }
            _ => {}
        }
    }
    if frame.is_none() {
        return Err(match out.ended_early {
            Some(e) => anyhow::anyhow!("{}: not a readable MCAP file: {e}", path.display()),
            None => anyhow::anyhow!(
                "{}: no `{METADATA_NAME}` metadata: not a markhold recording",
                path.display()
            ),
        });
    }
    Ok(out)
}
