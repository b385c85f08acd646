//! The camera images of a recording, frame by frame, for the commands that only need the
//! pixels (`markhold map`): read record by record like replay (memory does not grow with
//! the file), no loop rebuilt.

use crate::CoreError;
use std::collections::HashMap;
use std::path::Path;

use foxglove::schemas::CompressedImage;
use foxglove::Decode;
use markhold_exposure::{Frame, FrameMeta};

use super::replay::{decode_image, for_each_record, no_run_info, recording, run_info_of};
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
pub fn for_each_image<E: From<CoreError>>(
    path: &Path,
    every: u64,
    mut f: impl FnMut(&Frame) -> Result<(), E>,
) -> Result<ImagesRead, E> {
    use mcap::records::Record;

    let file = crate::params::open_regular(path, u64::MAX).map_err(|source| CoreError::File {
        action: "reading",
        path: path.to_path_buf(),
        source,
    })?;
    let src = std::io::BufReader::with_capacity(1 << 20, file);
    let every = every.max(1);
    let mut image_channels: HashMap<u16, bool> = HashMap::new();
    let mut frame: Option<Frame> = None;
    let mut out = ImagesRead::default();
    out.ended_early = for_each_record(path, src, |record| -> Result<(), E> {
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
                    return Ok(());
                }
                let Some(frame) = frame.as_mut() else {
                    return Err(recording(
                        path,
                        format!("an image before the `{METADATA_NAME}` metadata: not a markhold recording"),
                    )
                    .into());
                };
                let index = out.images;
                out.images += 1;
                if !index.is_multiple_of(every) {
                    return Ok(());
                }
                let img = CompressedImage::decode(&*data)
                    .map_err(|e| recording(path, format!("image {index}: {e}")))?;
                match img.format.as_str() {
                    "png" => {}
                    "jpeg" => out.lossy += 1,
                    other => {
                        return Err(recording(
                            path,
                            format!("image {index}: format {other:?}: expected png or jpeg"),
                        )
                        .into())
                    }
                }
                decode_image(&img.data, frame).map_err(|e| CoreError::RecordingPart {
                    path: path.to_path_buf(),
                    part: format!("image {index}"),
                    source: Box::new(e),
                })?;
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
        Ok(())
    })?;
    if frame.is_none() {
        return Err(no_run_info(path, out.ended_early).into());
    }
    Ok(out)
}
