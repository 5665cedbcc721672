//! Wavefront OBJ text of a triangle mesh, formatted in parallel.
//!
//! Lines: `v x y z` or `v x y z r g b` (positions as C's `%.9g`, colours `c / 255` as `%.6g`),
//! `vn nx ny nz` (`%.7g`) and `f a//a b//b c//c` or `f a b c` (1-based indices), after a given
//! header. `%.Pg` is formatted exactly as C and Python do: the value rounded (half to even, on its
//! exact binary value) to P significant digits, in fixed notation when its decimal exponent X
//! satisfies -4 <= X < P and in exponent notation (`e+XX`, at least two digits) otherwise,
//! trailing zeros and a trailing point removed. Chunks of lines are formatted on the rayon pool
//! and written in order, a bounded number at a time: no whole-file buffer.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use rayon::prelude::*;

use crate::error::{Error, Result};

/// Lines per chunk formatted by one task.
const CHUNK: usize = 1 << 15;

/// A triangle mesh to write as OBJ text.
#[derive(Debug, Clone, Copy)]
#[non_exhaustive]
pub struct ObjMesh<'a> {
    /// Written first, as is (comment lines).
    pub header: &'a str,
    /// Vertex positions, x, y, z of each point.
    pub points: &'a [f32],
    /// Vertex normals, 3 per point, or none.
    pub normals: Option<&'a [f32]>,
    /// Vertex colours 0..255, 3 per point (red, green, blue), or none.
    pub colors: Option<&'a [u8]>,
    /// Triangles: 3 0-based indices into the points each.
    pub faces: &'a [u32],
}

impl<'a> ObjMesh<'a> {
    /// A mesh of `points` and `faces` with optional normals and colours.
    pub fn new(
        header: &'a str,
        points: &'a [f32],
        normals: Option<&'a [f32]>,
        colors: Option<&'a [u8]>,
        faces: &'a [u32],
    ) -> ObjMesh<'a> {
        ObjMesh {
            header,
            points,
            normals,
            colors,
            faces,
        }
    }
}

/// Writes `mesh` as OBJ text to the file `path` (created or truncated); fails with
/// [`Error::FileWrite`] naming the file when the arrays do not hold whole triples, normals or
/// colours do not match the points, a face refers to no point, or the file cannot be written.
pub fn write_obj(path: &Path, mesh: &ObjMesh<'_>) -> Result<()> {
    let fail = |os_error: Option<i32>, reason: String| Error::FileWrite {
        path: path.to_path_buf(),
        os_error,
        reason,
    };
    let len = mesh.points.len();
    if len % 3 != 0
        || mesh.faces.len() % 3 != 0
        || mesh.normals.is_some_and(|v| v.len() != len)
        || mesh.colors.is_some_and(|c| c.len() != len)
    {
        return Err(fail(
            None,
            "the points, normals, colours or faces do not match".into(),
        ));
    }
    let n = len / 3;
    if mesh.faces.par_iter().any(|&v| v as usize >= n) {
        return Err(fail(
            None,
            "a face refers to a point that does not exist".into(),
        ));
    }
    let io = |e: std::io::Error| fail(e.raw_os_error(), e.to_string());
    let mut file = BufWriter::with_capacity(1 << 20, File::create(path).map_err(io)?);
    file.write_all(mesh.header.as_bytes()).map_err(io)?;
    let batch = CHUNK * 4 * rayon::current_num_threads().max(1);
    let with_normals = mesh.normals.is_some();
    for start in (0..n).step_by(batch) {
        let end = (start + batch).min(n);
        let chunks: Vec<Vec<u8>> = (start..end)
            .step_by(CHUNK)
            .collect::<Vec<_>>()
            .par_iter()
            .map(|&a| vertex_lines(mesh, a, (a + CHUNK).min(end)))
            .collect();
        for c in chunks {
            file.write_all(&c).map_err(io)?;
        }
    }
    if let Some(normals) = mesh.normals {
        write_chunks(&mut file, normals, batch, |out, v: &[f32]| {
            out.extend_from_slice(b"vn ");
            push_g(out, f64::from(v[0]), 7);
            out.push(b' ');
            push_g(out, f64::from(v[1]), 7);
            out.push(b' ');
            push_g(out, f64::from(v[2]), 7);
            out.push(b'\n');
        })
        .map_err(io)?;
    }
    write_chunks(&mut file, mesh.faces, batch, |out, f: &[u32]| {
        out.extend_from_slice(b"f ");
        for (i, &v) in f.iter().enumerate() {
            if i > 0 {
                out.push(b' ');
            }
            let index = u64::from(v) + 1;
            push_int(out, index);
            if with_normals {
                out.extend_from_slice(b"//");
                push_int(out, index);
            }
        }
        out.push(b'\n');
    })
    .map_err(io)?;
    file.flush().map_err(io)?;
    Ok(())
}

/// Formats the triples of `items` (one line each) a chunk per task, `batch` lines at a time,
/// and writes them in order.
fn write_chunks<T: Sync, W: Write>(
    file: &mut W,
    items: &[T],
    batch: usize,
    line: impl Fn(&mut Vec<u8>, &[T]) + Sync,
) -> std::io::Result<()> {
    for group in items.chunks(3 * batch) {
        let chunks: Vec<Vec<u8>> = group
            .par_chunks(3 * CHUNK)
            .map(|chunk| {
                let mut out = Vec::with_capacity(chunk.len() * 16);
                for item in chunk.chunks_exact(3) {
                    line(&mut out, item);
                }
                out
            })
            .collect();
        for c in chunks {
            file.write_all(&c)?;
        }
    }
    Ok(())
}

/// The `v` lines of points `a..b`.
fn vertex_lines(mesh: &ObjMesh<'_>, a: usize, b: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity((b - a) * 64);
    for i in a..b {
        out.extend_from_slice(b"v ");
        let p = &mesh.points[3 * i..3 * i + 3];
        push_g(&mut out, f64::from(p[0]), 9);
        out.push(b' ');
        push_g(&mut out, f64::from(p[1]), 9);
        out.push(b' ');
        push_g(&mut out, f64::from(p[2]), 9);
        if let Some(colors) = mesh.colors {
            for &c in &colors[3 * i..3 * i + 3] {
                out.push(b' ');
                push_g(&mut out, f64::from(c) / 255.0, 6);
            }
        }
        out.push(b'\n');
    }
    out
}

/// Appends the decimal digits of `v`.
fn push_int(out: &mut Vec<u8>, v: u64) {
    let mut digits = [0u8; 20];
    let mut i = digits.len();
    let mut v = v;
    loop {
        i -= 1;
        digits[i] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    out.extend_from_slice(&digits[i..]);
}

/// Appends `x` formatted as C's `%.{p}g` (`p` >= 1); "nan", "inf" and "-inf" for non-finite
/// values, as Python writes them.
pub(crate) fn push_g(out: &mut Vec<u8>, x: f64, p: usize) {
    use std::fmt::Write as _;
    if !x.is_finite() {
        out.extend_from_slice(if x.is_nan() {
            b"nan"
        } else if x > 0.0 {
            b"inf"
        } else {
            b"-inf"
        });
        return;
    }
    if x == 0.0 {
        out.extend_from_slice(if x.is_sign_negative() { b"-0" } else { b"0" });
        return;
    }
    let mut s = String::with_capacity(32);
    // The value rounded to p significant digits gives the exponent that decides the notation.
    let _ = write!(s, "{:.*e}", p - 1, x);
    let (mantissa, exponent) = s.split_once('e').unwrap_or((&s, "0"));
    let exponent: i32 = exponent.parse().unwrap_or(0);
    if exponent < -4 || exponent >= p as i32 {
        out.extend_from_slice(strip_zeros(mantissa).as_bytes());
        out.push(b'e');
        out.push(if exponent < 0 { b'-' } else { b'+' });
        let e = exponent.unsigned_abs();
        if e < 10 {
            out.push(b'0');
        }
        push_int(out, u64::from(e));
    } else {
        let mut f = String::with_capacity(32);
        let _ = write!(f, "{:.*}", (p as i32 - 1 - exponent) as usize, x);
        out.extend_from_slice(strip_zeros(&f).as_bytes());
    }
}

/// `s` without trailing zeros after a decimal point, and without the point if nothing follows.
fn strip_zeros(s: &str) -> &str {
    if !s.contains('.') {
        return s;
    }
    s.trim_end_matches('0').trim_end_matches('.')
}

#[cfg(test)]
mod tests {
    use super::*;

    fn g(x: f64, p: usize) -> String {
        let mut out = Vec::new();
        push_g(&mut out, x, p);
        String::from_utf8(out).unwrap()
    }

    #[test]
    fn percent_g_as_c() {
        // Expected strings from Python's "%.Pg" % x.
        let cases: [(f64, usize, &str); 16] = [
            (0.0, 9, "0"),
            (-0.0, 9, "-0"),
            (1.0, 9, "1"),
            (1234567.125, 9, "1234567.12"),
            (0.25, 1, "0.2"),
            (123456789.0, 9, "123456789"),
            (1234567890.0, 9, "1.23456789e+09"),
            (0.0001, 9, "0.0001"),
            (0.00001, 9, "1e-05"),
            (-1.5e-7, 7, "-1.5e-07"),
            (1e100, 6, "1e+100"),
            (2.0 / 3.0, 6, "0.666667"),
            (f64::from(0.1f32), 9, "0.100000001"),
            (-12.5, 7, "-12.5"),
            (999999.5, 6, "1e+06"),
            (9.9999995, 7, "9.999999"),
        ];
        for (x, p, expected) in cases {
            assert_eq!(g(x, p), expected, "{x} %.{p}g");
        }
        assert_eq!(g(f64::NAN, 9), "nan");
        let mut out = Vec::new();
        push_int(&mut out, 0);
        push_int(&mut out, 1234);
        assert_eq!(out, b"01234");
    }
}
