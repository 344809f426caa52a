//! `gprflow convert INPUT --to mcap`: a radar file (CMU-GPR folder, DZT, DT1/HD, or another
//! MCAP) to one of our recordings, through the loader the `ingest` stage plays
//! (`gprflow_ingest::load`).

use std::collections::BTreeMap;
use std::io::Write as _;
use std::path::Path;
use std::process::ExitCode;

use anyhow::{Context, Result};
use gprflow::record::{Recorder, RunMetadata};
use gprflow_ingest::SourceFormat;
use gprflow_ingest::load::{LoadOptions, Port, load};

/// Writes `input` as an MCAP recording at `output`: traces on `/gpr/trace`, sweeps on
/// `/lgpr/sweep`, IMU on `/imu/data`, wheel on `/wheel/odometry`, truth on `/truth/pose`.
///
/// # Errors
/// The reader's error (naming file, record and field) or a write error.
pub fn convert_to_mcap(input: &Path, format: SourceFormat, output: &Path) -> Result<ExitCode> {
    let loaded =
        load(input, format, &LoadOptions::default()).with_context(|| format!("{}: cannot convert", input.display()))?;
    let mut meta = RunMetadata::this_build();
    meta.graph_name = format!("convert {}", input.display());
    let first = loaded.messages.first().map_or(0, |m| m.1);
    let mut rec = Recorder::create_reproducible(output, &meta, u64::try_from(first).unwrap_or(0))?;
    let mut fields = BTreeMap::new();
    fields.insert("source".to_owned(), input.display().to_string());
    fields.insert("summary".to_owned(), loaded.summary.clone());
    fields.insert("skipped_records".to_owned(), loaded.dropped.len().to_string());
    rec.write_metadata("convert", fields)?;
    let mut channels = BTreeMap::new();
    let mut seqs: BTreeMap<Port, u64> = BTreeMap::new();
    for (port, stamp, data) in &loaded.messages {
        let ch = match channels.get(port) {
            Some(ch) => *ch,
            None => {
                let ch = rec.add_topic(port.topic(), port.msg_type())?;
                channels.insert(*port, ch);
                ch
            }
        };
        let seq = seqs.entry(*port).or_default();
        rec.write(ch, *seq, *stamp, data)?;
        *seq += 1;
    }
    rec.finish()?;
    let mut out = std::io::stdout().lock();
    writeln!(out, "{}: {}", input.display(), loaded.summary)?;
    for (port, n) in &seqs {
        writeln!(out, "  {:<28} {n} messages", port.topic())?;
    }
    for d in &loaded.dropped {
        writeln!(out, "  reported: {d}")?;
    }
    writeln!(out, "written to {}", output.display())?;
    Ok(ExitCode::SUCCESS)
}
