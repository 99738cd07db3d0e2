//! Plain CDR (OMG XCDR1), little-endian, as ROS 2 puts it on the wire and in MCAP: a 4-byte
//! encapsulation header `00 01 00 00`, then the fields in order, each primitive aligned to its
//! own size counted from the end of the header; strings are a `u32` length that includes the
//! terminating NUL, the bytes and the NUL; sequences a `u32` count and their elements; fixed
//! arrays just their elements.

/// `CDR_LE` with no options: what Fast-CDR (rmw_zenoh, rosbag2) writes on little-endian hosts.
pub const ENCAPSULATION_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Builds one CDR message.
#[derive(Debug)]
pub struct CdrWriter {
    buf: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    pub fn new() -> Self {
        Self::with_capacity(64)
    }

    pub fn with_capacity(bytes: usize) -> Self {
        let mut buf = Vec::with_capacity(bytes + 4);
        buf.extend_from_slice(&ENCAPSULATION_LE);
        CdrWriter { buf }
    }

    fn align(&mut self, size: usize) {
        let offset = self.buf.len() - 4;
        let pad = (size - offset % size) % size;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    pub fn bool(&mut self, v: bool) {
        self.buf.push(u8::from(v));
    }

    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A sequence's element count (its elements follow). Counts past `u32::MAX` cannot be
    /// written in CDR; the caller keeps messages far below that.
    pub fn len(&mut self, n: usize) {
        self.u32(u32::try_from(n).unwrap_or(u32::MAX));
    }

    pub fn string(&mut self, s: &str) {
        self.len(s.len() + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    /// A `uint8[]` sequence.
    pub fn bytes(&mut self, b: &[u8]) {
        self.len(b.len());
        self.buf.extend_from_slice(b);
    }

    pub fn finish(self) -> Vec<u8> {
        self.buf
    }
}

/// Why a CDR message could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CdrError {
    #[error("not CDR: the encapsulation header is missing or not plain CDR (got {0:02x?})")]
    Encapsulation(Vec<u8>),
    #[error("the message ends at byte {at} inside a field of {need} bytes")]
    Truncated { at: usize, need: usize },
    #[error("a string is not NUL-terminated UTF-8")]
    BadString,
    #[error("a sequence of {count} elements does not fit in the {left} bytes left")]
    Count { count: u32, left: usize },
}

/// Reads one CDR message (either byte order).
#[derive(Debug)]
pub struct CdrReader<'a> {
    data: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> CdrReader<'a> {
    /// Checks the encapsulation header (plain CDR, big- or little-endian).
    pub fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        let header = data
            .get(..4)
            .ok_or_else(|| CdrError::Encapsulation(data.to_vec()))?;
        let little = match (header[0], header[1]) {
            (0, 1) => true,
            (0, 0) => false,
            _ => return Err(CdrError::Encapsulation(header.to_vec())),
        };
        Ok(CdrReader {
            data: &data[4..],
            pos: 0,
            little,
        })
    }

    fn take(&mut self, size: usize, align: usize) -> Result<&'a [u8], CdrError> {
        let start = self.pos.div_ceil(align) * align;
        let end = start
            .checked_add(size)
            .filter(|&e| e <= self.data.len())
            .ok_or(CdrError::Truncated {
                at: start,
                need: size,
            })?;
        self.pos = end;
        Ok(&self.data[start..end])
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], CdrError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, N)?);
        if !self.little {
            out.reverse();
        }
        Ok(out)
    }

    pub fn u8(&mut self) -> Result<u8, CdrError> {
        Ok(self.take(1, 1)?[0])
    }

    pub fn bool(&mut self) -> Result<bool, CdrError> {
        Ok(self.u8()? != 0)
    }

    pub fn u32(&mut self) -> Result<u32, CdrError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    pub fn i32(&mut self) -> Result<i32, CdrError> {
        Ok(i32::from_le_bytes(self.array()?))
    }

    pub fn f64(&mut self) -> Result<f64, CdrError> {
        Ok(f64::from_le_bytes(self.array()?))
    }

    /// A sequence's element count, checked against what is left (each element is at least
    /// `min_size` bytes), so a hostile count cannot make the caller allocate.
    pub fn len(&mut self, min_size: usize) -> Result<usize, CdrError> {
        let count = self.u32()?;
        let left = self.data.len() - self.pos;
        if (count as usize).saturating_mul(min_size.max(1)) > left {
            return Err(CdrError::Count { count, left });
        }
        Ok(count as usize)
    }

    pub fn string(&mut self) -> Result<String, CdrError> {
        let n = self.len(1)?;
        if n == 0 {
            return Ok(String::new());
        }
        let bytes = self.take(n, 1)?;
        match bytes.split_last() {
            Some((0, text)) => std::str::from_utf8(text)
                .map(String::from)
                .map_err(|_| CdrError::BadString),
            _ => Err(CdrError::BadString),
        }
    }

    /// A `uint8[]` sequence, borrowed.
    pub fn bytes(&mut self) -> Result<&'a [u8], CdrError> {
        let n = self.len(1)?;
        self.take(n, 1)
    }

    /// A fixed `float64[N]` array.
    pub fn f64s<const N: usize>(&mut self) -> Result<[f64; N], CdrError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64()?;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_aligned_from_the_end_of_the_header() {
        let mut w = CdrWriter::new();
        w.u8(7);
        w.f64(1.5);
        w.string("ab");
        w.u32(9);
        let bytes = w.finish();
        assert_eq!(&bytes[..4], &ENCAPSULATION_LE);
        // u8 at 0, f64 padded to 8, string length at 16, "ab\0" at 20..23, u32 at 24.
        assert_eq!(bytes.len(), 4 + 28);
        assert_eq!(&bytes[4 + 16..4 + 23], &[3, 0, 0, 0, b'a', b'b', 0]);
        let mut r = CdrReader::new(&bytes).expect("header");
        assert_eq!(r.u8(), Ok(7));
        assert_eq!(r.f64(), Ok(1.5));
        assert_eq!(r.string().as_deref(), Ok("ab"));
        assert_eq!(r.u32(), Ok(9));
        assert!(matches!(r.u32(), Err(CdrError::Truncated { .. })));
    }

    #[test]
    fn hostile_counts_and_headers_are_errors() {
        let mut w = CdrWriter::new();
        w.u32(u32::MAX);
        let bytes = w.finish();
        assert!(matches!(
            CdrReader::new(&bytes).expect("header").bytes(),
            Err(CdrError::Count { .. })
        ));
        assert!(CdrReader::new(&[0x00, 0x07, 0, 0]).is_err());
        assert!(CdrReader::new(&[0x00]).is_err());
        let big_endian = [0u8, 0, 0, 0, 0, 0, 0, 5];
        assert_eq!(CdrReader::new(&big_endian).expect("BE").u32(), Ok(5));
    }
}
