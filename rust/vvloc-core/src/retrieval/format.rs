//! The `.vvidx` file format of a [`DescriptorIndex`] (version 1), all integers little-endian:
//!
//! | offset | size      | field                                                        |
//! |--------|-----------|--------------------------------------------------------------|
//! | 0      | 8         | magic `b"VVLOCIDX"`                                          |
//! | 8      | 4         | version (u32) = 1                                            |
//! | 12     | 4         | dtype (u32): 0 float32, 1 float16, 2 bfloat16, 3 int8      |
//! | 16     | 8         | N (u64), number of entries                                   |
//! | 24     | 8         | d (u64), dimension                                           |
//! | 32     | 8         | checksum (u64) of bytes 8..32 and of the payload (below)     |
//! | 40     | N·d·4     | descriptors, float32, row-major (N, d)                       |
//! |        | N·8       | group ids (i64)                                              |
//! |        | N·8       | sequence numbers (i64)                                       |
//!
//! The checksum folds every 8-byte little-endian word w (the tail zero-padded) into
//! `h = (h ^ w) · 0x100000001b3` starting from `0xcbf29ce484222325` (FNV-1a constants, word-wise):
//! each step is a bijection of h, so any change to a single word is always detected. The
//! compressed scan copy is not stored; it is rebuilt on load. Files are written to a temporary
//! sibling, flushed, then renamed over the target, so a reader never sees a partial file.

use super::{DescriptorIndex, Dtype};
use crate::{Error, Result};
use std::io::{Read, Write};
use std::path::Path;

const MAGIC: &[u8; 8] = b"VVLOCIDX";
const VERSION: u32 = 1;
const HEADER: usize = 40;

pub(super) fn checksum(parts: &[&[u8]]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for part in parts {
        let mut chunks = part.chunks_exact(8);
        for c in &mut chunks {
            h = (h ^ u64::from_le_bytes(c.try_into().unwrap())).wrapping_mul(0x0100_0000_01b3);
        }
        let rem = chunks.remainder();
        if !rem.is_empty() {
            let mut w = [0u8; 8];
            w[..rem.len()].copy_from_slice(rem);
            h = (h ^ u64::from_le_bytes(w)).wrapping_mul(0x0100_0000_01b3);
        }
    }
    h
}

fn io_err(path: &Path, e: std::io::Error) -> Error {
    Error::Io {
        path: path.display().to_string(),
        msg: e.to_string(),
    }
}

/// Serialises the index into the version-1 byte layout; [`Error::Memory`] (not an abort)
/// when the bytes cannot be allocated.
pub fn to_bytes(index: &DescriptorIndex) -> Result<Vec<u8>> {
    let n = index.len();
    let total = n
        .checked_mul(index.dim() * 4 + 16)
        .and_then(|p| p.checked_add(HEADER));
    let mut out = Vec::new();
    total
        .and_then(|t| out.try_reserve_exact(t).ok())
        .ok_or_else(|| Error::Memory {
            arg: "index",
            what: format!("the {n} entries' bytes"),
        })?;
    let mut meta = Vec::with_capacity(24);
    meta.extend_from_slice(&VERSION.to_le_bytes());
    meta.extend_from_slice(&index.dtype().code().to_le_bytes());
    meta.extend_from_slice(&(n as u64).to_le_bytes());
    meta.extend_from_slice(&(index.dim() as u64).to_le_bytes());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&meta);
    out.extend_from_slice(&[0; 8]); // the checksum, once the payload is written
    for i in 0..n {
        for v in index.row(i) {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    for v in index.groups().iter().chain(index.seqs()) {
        out.extend_from_slice(&v.to_le_bytes());
    }
    let sum = checksum(&[&meta, &out[HEADER..]]);
    out[HEADER - 8..HEADER].copy_from_slice(&sum.to_le_bytes());
    Ok(out)
}

fn bad(msg: &str) -> Error {
    Error::Format(format!("not a valid vvloc descriptor index: {msg}"))
}

/// The header's dtype, N and d, checked against the length `len` of the whole file: `head`
/// holds its first `min(len, 40)` bytes. Any inconsistency is an [`Error::Format`].
fn parse_header(head: &[u8], len: u64) -> Result<(Dtype, u64, u64)> {
    if head.len() < HEADER || len < HEADER as u64 {
        return Err(bad("file is shorter than the 40-byte header (truncated?)"));
    }
    if &head[..8] != MAGIC {
        return Err(bad("wrong magic bytes"));
    }
    let u32_at = |o: usize| u32::from_le_bytes(head[o..o + 4].try_into().unwrap());
    let u64_at = |o: usize| u64::from_le_bytes(head[o..o + 8].try_into().unwrap());
    let version = u32_at(8);
    if version != VERSION {
        return Err(bad(&format!(
            "unsupported version {version} (this build reads version {VERSION})"
        )));
    }
    let dtype = Dtype::from_code(u32_at(12)).ok_or_else(|| bad("unknown dtype code"))?;
    let (n, d) = (u64_at(16), u64_at(24));
    let expected = n
        .checked_mul(d)
        .and_then(|nd| nd.checked_mul(4))
        .and_then(|b| b.checked_add(n.checked_mul(16)?))
        .and_then(|b| b.checked_add(HEADER as u64))
        .ok_or_else(|| bad("header sizes overflow"))?;
    if d == 0 {
        return Err(bad(
            "header says d=0 (descriptors have at least one dimension)",
        ));
    }
    if expected != len {
        return Err(bad(&format!(
            "header says N={n}, d={d} ({expected} bytes) but the file has {len} bytes (truncated?)"
        )));
    }
    Ok((dtype, n, d))
}

/// Parses a version-1 file's bytes; any inconsistency is an [`Error::Format`].
pub fn from_bytes(bytes: &[u8]) -> Result<DescriptorIndex> {
    let (dtype, n, d) = parse_header(&bytes[..bytes.len().min(HEADER)], bytes.len() as u64)?;
    let payload = &bytes[HEADER..];
    let stored = u64::from_le_bytes(bytes[32..HEADER].try_into().unwrap());
    if checksum(&[&bytes[8..32], payload]) != stored {
        return Err(bad("checksum mismatch (corrupted file)"));
    }
    let (n, d) = (n as usize, d as usize);
    crate::error::check_alloc::<f32>("index", n * d)?; // the rows, then the index's own copy
    let (desc, rest) = payload.split_at(n * d * 4);
    let (groups, seqs) = rest.split_at(n * 8);
    let f32s: Vec<f32> = desc
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let i64s = |b: &[u8]| -> Vec<i64> {
        b.chunks_exact(8)
            .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
            .collect()
    };
    DescriptorIndex::from_rows(&f32s, d, dtype, Some(&i64s(groups)), Some(&i64s(seqs)))
        .map_err(|e| bad(&format!("invalid contents: {e}")))
}

impl DescriptorIndex {
    /// Writes the index to `path` atomically (temporary sibling + rename). A plain version for
    /// Rust callers: the new file has the default mode and a symbolic link at `path` is
    /// replaced; Python's `DescriptorIndex.save` writes [`to_bytes`] with vvloc's atomic
    /// writer instead (a file's mode kept, links followed, devices written into).
    pub fn save(&self, path: &Path) -> Result<()> {
        let bytes = to_bytes(self)?;
        let name = path
            .file_name()
            .ok_or_else(|| Error::value("path", format!("not a file path: {}", path.display())))?;
        let mut tmp_name = name.to_os_string();
        // Unique per process and call, so concurrent saves never share a temporary file.
        static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let count = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        tmp_name.push(format!(".tmp{}-{count}", std::process::id()));
        let tmp = path.with_file_name(tmp_name);
        let write = || -> std::io::Result<()> {
            let mut f = std::fs::File::create(&tmp)?;
            f.write_all(&bytes)?;
            f.sync_all()?;
            std::fs::rename(&tmp, path)
        };
        write().map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            io_err(path, e)
        })
    }

    /// Reads an index written by [`DescriptorIndex::save`]; a truncated, corrupted or foreign
    /// file is an [`Error::Format`], a missing or unreadable one an [`Error::Io`].
    ///
    /// The header is checked against the file's length before the rest is read: a foreign or
    /// truncated file of gigabytes is refused without reading it into memory.
    pub fn load(path: &Path) -> Result<DescriptorIndex> {
        let named = |e: Error| match e {
            Error::Format(m) => Error::Format(format!("{}: {m}", path.display())),
            other => other,
        };
        let meta = std::fs::metadata(path).map_err(|e| io_err(path, e))?;
        if !meta.is_file() {
            // a pipe would block the open, and a device's length says nothing
            return Err(Error::Io {
                path: path.display().to_string(),
                msg: "not a regular file (a folder, device or pipe)".into(),
            });
        }
        let mut f = std::fs::File::open(path).map_err(|e| io_err(path, e))?;
        let len = f.metadata().map_err(|e| io_err(path, e))?.len();
        let mut head = Vec::with_capacity(HEADER);
        (&mut f)
            .take(HEADER as u64)
            .read_to_end(&mut head)
            .map_err(|e| io_err(path, e))?;
        parse_header(&head, len).map_err(named)?;
        let mut bytes = head;
        usize::try_from(len)
            .ok()
            .and_then(|l| bytes.try_reserve_exact(l - HEADER).ok())
            .ok_or_else(|| Error::Memory {
                arg: "path",
                what: format!("the {len} bytes of {}", path.display()),
            })?;
        f.read_to_end(&mut bytes).map_err(|e| io_err(path, e))?;
        from_bytes(&bytes).map_err(named)
    }
}
