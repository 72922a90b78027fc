//! The layout of a TIFF file checked before the decoder trusts it: the first IFD's entries
//! lie inside the file, each chunk's offsets and sizes are sane, and a header cannot claim more
//! samples than the file's bytes can fill.

use super::*;

/// Bytes of one value of each TIFF field type; 0 for types the decoder does not know.
pub(super) fn type_bytes(t: u16) -> u64 {
    match t {
        1 | 2 | 6 | 7 => 1,
        3 | 8 => 2,
        4 | 9 | 11 | 13 => 4,
        5 | 10 | 12 | 16 | 17 | 18 => 8,
        _ => 0,
    }
}

/// Checks that the first IFD and every value it points to lie inside the file. The decoder
/// allocates room for a tag's values before it reads them, so a few bytes that claim a tag
/// of millions of values would otherwise cost that much memory.
pub(super) fn check_first_ifd<R: Read + Seek>(r: &mut R, file_len: u64) -> Result<(), ReadError> {
    use std::io::SeekFrom;
    let mut head = [0u8; 16];
    r.seek(SeekFrom::Start(0))?;
    let n = r.by_ref().take(16).read(&mut head)?;
    if n < 8 {
        return Err(ReadError::invalid(
            "not a TIFF file: it is shorter than a TIFF header",
        ));
    }
    let big_endian = match &head[..2] {
        b"II" => false,
        b"MM" => true,
        // The decoder names a bad signature itself.
        _ => return Ok(()),
    };
    let u16_at = |b: &[u8]| {
        let a = [b[0], b[1]];
        if big_endian {
            u16::from_be_bytes(a)
        } else {
            u16::from_le_bytes(a)
        }
    };
    let u32_at = |b: &[u8]| {
        let a = [b[0], b[1], b[2], b[3]];
        u64::from(if big_endian {
            u32::from_be_bytes(a)
        } else {
            u32::from_le_bytes(a)
        })
    };
    let u64_at = |b: &[u8]| {
        let a: [u8; 8] = b[..8].try_into().expect("8 bytes");
        if big_endian {
            u64::from_be_bytes(a)
        } else {
            u64::from_le_bytes(a)
        }
    };
    // Data a header points to past the end is what a cut-off download looks like; a hostile
    // header gets the same answer.
    //
    // (bytes of the entry count, of an entry, of a value held in the entry itself)
    let (ifd, count_len, entry_len, inline) = match u16_at(&head[2..]) {
        42 => (u32_at(&head[4..]), 2u64, 12u64, 4u64),
        43 if n >= 16 => (u64_at(&head[8..]), 8, 20, 8),
        _ => return Ok(()),
    };
    if ifd.checked_add(count_len).is_none_or(|end| end > file_len) {
        return Err(ReadError::Truncated);
    }
    r.seek(SeekFrom::Start(ifd))?;
    let mut buf = [0u8; 20];
    r.read_exact(&mut buf[..count_len as usize])?;
    let entries = if count_len == 2 {
        u64::from(u16_at(&buf))
    } else {
        u64_at(&buf)
    };
    let end = entries
        .checked_mul(entry_len)
        .and_then(|b| b.checked_add(ifd + count_len));
    if end.is_none_or(|end| end > file_len) {
        return Err(ReadError::Truncated);
    }
    for _ in 0..entries {
        let e = &mut buf[..entry_len as usize];
        r.read_exact(e)?;
        let ty = u16_at(&e[2..]);
        let (count, offset) = if entry_len == 12 {
            (u32_at(&e[4..]), u32_at(&e[8..]))
        } else {
            (u64_at(&e[4..]), u64_at(&e[12..]))
        };
        let bytes = count.saturating_mul(type_bytes(ty));
        if bytes > inline && offset.checked_add(bytes).is_none_or(|end| end > file_len) {
            return Err(ReadError::Truncated);
        }
    }
    r.seek(SeekFrom::Start(0))?;
    Ok(())
}

/// The most bytes one byte of compressed data can decode to, for each compression the
/// decoder knows; the bound a header's claims are held to before anything is allocated.
/// PackBits turns 2 bytes into 128; an LZW code (9 to 12 bits) expands to at most 4096 bytes;
/// deflate's ratio is at most 1032:1; a zstd RLE block turns 4 bytes into 128 KiB.
pub(super) fn codec_expansion<R: Read + Seek>(dec: &mut Decoder<R>) -> Result<u64, ReadError> {
    let code: u16 = dec
        .find_tag_unsigned(Tag::Compression)
        .map_err(tiff_error)?
        .unwrap_or(1);
    Ok(match code {
        1 => 1,
        32773 => 64,
        5 => 4096,
        8 | 32946 => 1032,
        // zstd, and codecs the decoder will refuse anyway.
        _ => 32768,
    })
}

/// Checks every chunk lies inside the file, so a cut-off download reports `Truncated` up front
/// instead of a decompressor error halfway through. Returns the bytes each chunk holds (0 for
/// sparse chunks: GDAL's SPARSE_OK writes offset 0 / byte count 0 for blocks that hold only
/// nodata), and the bytes of image data in the file: the union of the chunks, since many
/// chunks may point at the same bytes.
pub(super) fn chunk_layout_check<R: Read + Seek>(
    dec: &mut Decoder<R>,
    file_len: u64,
) -> Result<Chunks, ReadError> {
    let (offsets_tag, counts_tag) = match dec.get_chunk_type() {
        ChunkType::Strip => (Tag::StripOffsets, Tag::StripByteCounts),
        ChunkType::Tile => (Tag::TileOffsets, Tag::TileByteCounts),
    };
    let offsets = dec
        .find_tag_unsigned_vec::<u64>(offsets_tag)
        .map_err(tiff_error)?
        .unwrap_or_default();
    let counts = dec
        .find_tag_unsigned_vec::<u64>(counts_tag)
        .map_err(tiff_error)?
        .unwrap_or_default();
    if offsets.len() != counts.len() {
        return Err(ReadError::invalid(format!(
            "{} chunk offsets but {} chunk byte counts",
            offsets.len(),
            counts.len()
        )));
    }
    let mut ranges = Vec::with_capacity(offsets.len());
    for (&offset, &count) in offsets.iter().zip(&counts) {
        if count > 0 {
            let end = offset.checked_add(count).filter(|&end| end <= file_len);
            ranges.push((offset, end.ok_or(ReadError::Truncated)?));
        }
    }
    ranges.sort_unstable();
    let (mut present, mut reached) = (0u64, 0u64);
    for (start, end) in ranges {
        present += end.saturating_sub(start.max(reached));
        reached = reached.max(end);
    }
    Ok(Chunks {
        offsets,
        counts,
        present,
    })
}

/// Where a file's chunks lie, each inside the file.
pub(super) struct Chunks {
    pub(super) offsets: Vec<u64>,
    /// Bytes of each chunk; 0 for a sparse one.
    pub(super) counts: Vec<u64>,
    /// Bytes of image data, counted once where chunks share them.
    pub(super) present: u64,
}

pub(super) fn largest_chunk_samples<R: Read + Seek>(
    dec: &Decoder<R>,
    cols: usize,
    rows: usize,
) -> Result<u64, ReadError> {
    let (cw, ch) = dec.chunk_dimensions();
    let (cw, ch) = (u64::from(cw), u64::from(ch));
    match dec.get_chunk_type() {
        ChunkType::Strip => Ok(cols as u64 * ch.min(rows as u64)),
        ChunkType::Tile => {
            // Tiles wider than the image are legal, but a tile many times the image's size
            // is a corrupt or hostile header. The decoder fills whole tiles, padding included.
            let most = (cols as u64).max(4096) * (rows as u64).max(4096);
            if cw.checked_mul(ch).is_none_or(|n| n > most) {
                return Err(ReadError::invalid(format!(
                    "implausible tile size {cw} x {ch}"
                )));
            }
            Ok(cw * ch)
        }
    }
}
