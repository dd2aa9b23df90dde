//! Format detection from a file's first bytes, for data that arrives without a file name (service
//! uploads, request bodies).
//!
//! [`sniff`] looks at a prefix of the content ([`SNIFF_LEN`] bytes are plenty) and names the
//! [`Format`], or `None` when nothing matches:
//!
//! | content | answer |
//! |---|---|
//! | `ply` line | `ply` |
//! | `ASTM-E57` signature | `e57` |
//! | `LASF` signature, compression bits of the point format clear / set | `las` / `laz` (`copc.laz` when the first VLR is COPC's info VLR) |
//! | first keyword line of a PCD header (`VERSION`, `FIELDS`, …), or `# .PCD`; for a binary body, the header lines up to `DATA binary…` (after any comments) | `pcd` |
//! | first token `OFF`, `COFF`, `NOFF`, `CNOFF`, `STOFF` … | `off` |
//! | lines starting `v `, `f `, `vn `, `o `, `g `… (with at least one `v`) | `obj` |
//! | a lone count line, then lines of ≥ 3 numbers | `pts` |
//! | lines of ≥ 3 numbers (space, tab, comma or semicolon separated) | `xyz` |
//!
//! KITTI `.bin` scans are raw `f32` records with no signature: they are never sniffed and must be
//! named explicitly. Sniffing only picks a reader; the reader itself then validates the file.

use super::Format;

/// How many leading bytes [`sniff`] needs at most.
pub const SNIFF_LEN: usize = 4096;

/// Byte offset of the point data record format in a LAS public header.
const LAS_FORMAT_OFFSET: usize = 104;

/// The keywords of PCD header lines.
const PCD: [&str; 9] = [
    "VERSION", "FIELDS", "COLUMNS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "POINTS",
];

/// The text before a PCD body: everything up to and including a line starting `DATA binary`
/// (binary or binary_compressed), when that text is UTF-8.
fn pcd_header(head: &[u8]) -> Option<&str> {
    let mut at = 0;
    for line in head.split_inclusive(|&b| b == b'\n') {
        at += line.len();
        if line.starts_with(b"DATA binary") {
            return std::str::from_utf8(&head[..at]).ok();
        }
    }
    None
}

/// True when the LAZ content starting with `head` is COPC: its first VLR, right after the public
/// header, is the COPC info VLR (user `copc`, record 1), as COPC 1.0 requires.
fn is_copc(head: &[u8]) -> bool {
    let Some(size) = head
        .get(94..96)
        .map(|b| usize::from(u16::from_le_bytes([b[0], b[1]])))
    else {
        return false;
    };
    // A VLR header: reserved (2 bytes), user id (16, NUL-padded), record id (2).
    let user = head.get(size + 2..size + 18);
    let record = head.get(size + 18..size + 20);
    user.is_some_and(|u| u.starts_with(b"copc\0")) && record == Some(&[1, 0][..])
}

/// The format of content starting with `head` (PLY, LAS, LAZ, COPC, E57, PCD in any of its
/// three encodings, OFF, OBJ, PTS, XYZ), or `None`. A COPC file (its first VLR is the COPC info
/// VLR) sniffs as COPC, so a service upload is written back as COPC, not as a LAZ carrying a
/// stale COPC layout (issue 51).
pub fn sniff(head: &[u8]) -> Option<Format> {
    if head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") {
        return Some(Format::Ply);
    }
    if head.starts_with(super::e57::SIGNATURE) {
        return Some(Format::E57);
    }
    if head.starts_with(b"LASF") {
        // Bit 7 (LASzip) or bit 6 (old LASzip) of the point data record format marks LAZ.
        let compressed = head.get(LAS_FORMAT_OFFSET).is_some_and(|f| f & 0xC0 != 0);
        return Some(if !compressed {
            Format::Las
        } else if is_copc(head) {
            Format::Copc
        } else {
            Format::Laz
        });
    }
    // A binary PCD body follows its text header: judge the header alone, the lines before the
    // body (the bytes after `DATA binary` are not text).
    if let Some(header) = pcd_header(head) {
        let mut lines = header.lines().map(str::trim).filter(|l| !l.is_empty());
        let first = lines.clone().next().unwrap_or_default();
        let keyword = lines
            .find(|l| !l.starts_with('#'))
            .and_then(|l| l.split_whitespace().next())
            .unwrap_or_default();
        if first.starts_with("# .PCD") || PCD.contains(&keyword) {
            return Some(Format::Pcd);
        }
    }
    // Everything else is text: judge complete lines only (the last one may be cut off).
    let text = match head.iter().rposition(|&b| b == b'\n') {
        Some(end) if head.len() == SNIFF_LEN => &head[..end],
        _ => head,
    };
    let text = std::str::from_utf8(text).ok()?;
    let mut lines = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .peekable();
    let first = *lines.peek()?;
    if first.starts_with("# .PCD") {
        return Some(Format::Pcd);
    }
    let keyword = first.split_whitespace().next()?.to_ascii_uppercase();
    if PCD.contains(&keyword.as_str()) {
        return Some(Format::Pcd);
    }
    if keyword.ends_with("OFF")
        && keyword
            .trim_end_matches("OFF")
            .chars()
            .all(|c| matches!(c, 'C' | 'N' | 'S' | 'T'))
    {
        return Some(Format::Off);
    }
    // Drop comment lines (`#`, `//`) for the remaining text formats.
    let content: Vec<&str> = lines
        .filter(|l| !l.starts_with('#') && !l.starts_with("//"))
        .take(16)
        .collect();
    let first = *content.first()?;
    let obj_keyword = |l: &str| {
        matches!(
            l.split_whitespace().next(),
            Some(
                "v" | "vn" | "vt" | "vp" | "f" | "l" | "p" | "o" | "g" | "s" | "mtllib" | "usemtl"
            )
        )
    };
    if content.iter().all(|l| obj_keyword(l))
        && content
            .iter()
            .any(|l| l.split_whitespace().next() == Some("v"))
    {
        return Some(Format::Obj);
    }
    let numbers = |l: &str| -> Option<usize> {
        let fields: Vec<&str> = l
            .split(|c: char| c.is_whitespace() || c == ',' || c == ';')
            .filter(|t| !t.is_empty())
            .collect();
        fields
            .iter()
            .all(|t| t.parse::<f64>().is_ok())
            .then_some(fields.len())
    };
    let rest_are_points = |from: usize| {
        let rest = &content[from..];
        !rest.is_empty() && rest.iter().all(|l| numbers(l).is_some_and(|n| n >= 3))
    };
    if first.parse::<u64>().is_ok() && rest_are_points(1) {
        return Some(Format::Pts);
    }
    if rest_are_points(0) {
        return Some(Format::Xyz);
    }
    None
}

#[cfg(test)]
mod tests {
    use super::sniff;
    use crate::io::Format;

    #[test]
    fn formats_as_the_enum() {
        assert_eq!(sniff(b"ply\nformat ascii 1.0\n"), Some(Format::Ply));
        assert_eq!(sniff(b"0 0 0\n1 0 0\n0 1 0\n"), Some(Format::Xyz));
        assert_eq!(sniff(b"hello\n"), None);
        // Issue 12: a binary PCD body after the header.
        let mut pcd = b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nDATA binary\n".to_vec();
        pcd.extend_from_slice(&[0xff, 0xfe, 0x80, 0x81]);
        pcd.resize(super::SNIFF_LEN, 0x9f);
        assert_eq!(sniff(&pcd), Some(Format::Pcd));
    }

    /// Issue 15, item 4: binary and binary_compressed PCD are told by their header alone, also
    /// when it opens with other comments or its keywords in another order.
    #[test]
    fn issue15_binary_pcd_by_content() {
        for (head, data) in [
            (
                "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n",
                "binary",
            ),
            (
                "# made by a scanner\n# second comment\nFIELDS x y z\n",
                "binary_compressed",
            ),
            ("WIDTH 2\nHEIGHT 1\nFIELDS x y z\n", "binary"),
        ] {
            let mut pcd =
                format!("{head}SIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 2\nDATA {data}\n")
                    .into_bytes();
            pcd.extend_from_slice(&[0x80, 0xff, 0x00, 0x3f, 0xc0, 0x0a, 0xfe]);
            pcd.resize(pcd.len() + 100, 0xaa);
            assert_eq!(sniff(&pcd), Some(Format::Pcd), "{head}");
        }
        // A binary body after lines that are not a PCD header is not PCD.
        let mut other = b"# hello\nsomething else\nDATA binary\n".to_vec();
        other.extend_from_slice(&[0xff, 0xfe]);
        assert_eq!(sniff(&other), None);
    }

    #[test]
    fn formats_by_content() {
        assert_eq!(sniff(b"ply\nformat ascii 1.0\n"), Some(Format::Ply));
        assert_eq!(sniff(b"ASTM-E57\0\0\x01\0"), Some(Format::E57));
        let mut las = b"LASF".to_vec();
        las.resize(227, 0);
        assert_eq!(sniff(&las), Some(Format::Las));
        las[104] = 0x80 | 3;
        assert_eq!(sniff(&las), Some(Format::Laz));
        assert_eq!(sniff(b"# .PCD v0.7\nVERSION 0.7\n"), Some(Format::Pcd));
        assert_eq!(sniff(b"VERSION 0.7\nFIELDS x y z\n"), Some(Format::Pcd));
        assert_eq!(sniff(b"OFF\n3 1 0\n0 0 0\n"), Some(Format::Off));
        assert_eq!(sniff(b"COFF 8 6 12\n"), Some(Format::Off));
        assert_eq!(
            sniff(b"# made by hand\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"),
            Some(Format::Obj)
        );
        assert_eq!(sniff(b"3\n0 0 0 5\n1 0 0 5\n0 1 0 5\n"), Some(Format::Pts));
        assert_eq!(
            sniff(b"//X Y Z\n0,0,0\n1,0,0\n0,1,0.5\n"),
            Some(Format::Xyz)
        );
        assert_eq!(sniff(b"0 0 0\n1 0 0\n0 1 0\n"), Some(Format::Xyz));
    }

    #[test]
    fn unknown_content() {
        assert_eq!(sniff(b""), None);
        assert_eq!(sniff(b"hello world\n"), None);
        assert_eq!(sniff(&[0u8, 159, 146, 150, 1, 2, 3]), None);
        assert_eq!(sniff(b"{\"json\": true}"), None);
        assert_eq!(sniff(b"1 2\n3 4\n"), None);
        assert_eq!(sniff(b"LAS"), None);
    }
}
