//! numpy's .npy format for a float32 grid: what `patchwork tile --out x.npy` and the bench write.

use std::path::Path;

/// Writes a float32 numpy array (`shape` rows × cols).
pub fn write_npy(path: &Path, rows: usize, cols: usize, data: &[f32]) -> std::io::Result<()> {
    let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({rows}, {cols}), }}");
    let pad = 64 - (10 + header.len() + 1) % 64;
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&((header.len() + pad + 1) as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend(std::iter::repeat_n(b' ', pad));
    bytes.push(b'\n');
    for z in data {
        bytes.extend_from_slice(&z.to_le_bytes());
    }
    std::fs::write(path, bytes)
}
