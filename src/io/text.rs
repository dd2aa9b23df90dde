//! Text point clouds (`.xyz`, `.txt`, `.pts`); the line helpers it shares with the OBJ, OFF and
//! PCD backends are in `io/lines.rs`.
//!
//! # Brief overview
//!
//! * **XYZ** (`.xyz`, `.txt`): one point per line, columns separated by whitespace or commas. The
//!   first three columns are x, y and z; further columns (intensity, colour, normals…) are kept as
//!   `F64` fields named from a header comment such as `//X Y Z Intensity` or `# x y z r g b` when
//!   one matches the column count, else `c3`, `c4`, …
//! * **PTS** (`.pts`, Leica style): the same, preceded by a line holding the point count.
//!
//! ```text
//!  # scanned 2024-05-01          <- comment lines (`#` or `//`) before the points: TextMeta::header
//!  //X Y Z Intensity             <- names the columns when it has as many entries as a point line
//!  17238                         <- PTS only: the point count (rewritten with the sink's count)
//!  1.5 2.25 -0.5 0.31            <- points: x y z, then the extra columns c3, c4…
//!  # end                         <- comment lines after the last point: TextTrailer::tail
//! ```
//!
//! The reader is truly streaming: it holds one line and one batch at a time, never the file, so
//! an XYZ source does not know its point count (`SourceInfo::len` is `None`); a PTS source takes
//! it from the count line and checks it. A PTS file with several point blocks (a second count
//! line) is reported as unsupported.
//! The writer keeps the separator (`" "`, `"\t"`, `","`, `", "`…), the line terminator and the
//! comment lines before and after the points. Comment and blank lines *between* points are
//! dropped, because a streaming sink cannot know about them before it writes the points.
//!
//! Numbers are written with Rust's shortest round-trip formatting (`{}`); `f32` fields of a
//! foreign layout (KITTI, binary PLY) are written as `f32`, so a value read from a float file
//! prints as the short decimal it came from. Positions whose x, y, z fields are integers (LAS's
//! scaled `I32`) print as the shortest text that round-trips the decoded `f64` position, never
//! rounded to whole units. `nan` and `inf` are accepted and delivered as they are.
//! Faces cannot be stored in these formats; a sink ignores [`Extras::faces`].
//!
//! **Noise flag.** A sink created with [`SinkOptions::noise_flag`] ([`TextSink::create_with`])
//! appends a column to every point line, `1` for points flagged [`FLAG_NOISE`] and `0` otherwise,
//! after the file's separator. The comment line that names the columns (`//X Y Z Intensity`,
//! `# x,y,z`) gets `noise` in its own separator style, and the `# x y z …` line written for a
//! foreign XYZ output lists it; without such a line only the column is added (it then reads back
//! as `c3`, `c4`, …). A column already named `noise` is overwritten instead.
//!
//! **Normals.** With [`SinkOptions::normals`] the columns `nx ny nz curvature structure` come
//! before the noise column and are named the same way; the normal and curvature print as `f32`
//! (shortest text), the class as an integer. A column already named `nx` (or `normal_x`, …) is
//! overwritten instead (see [the I/O overview](super#normals)).

use std::path::Path;

use super::lines::{
    LineEnding, LineReader, LineSink, coord_types, default_names, encode_f64_record, extra_fields,
    f64_schema, is_comment_or_blank, parse_f64, parse_u64, push_value, show, split_eol, trim,
};
use super::tally::{Tally, check_batch};
use super::{
    AtomicFile, BodyStats, Extras, Format, Input, IoError, Meta, NOISE_FIELD, NormalField,
    NormalNames, Sink, SinkOptions, Source, SourceInfo, Trailer,
};
use crate::points::{FLAG_NOISE, PointBatch, Rounding, ScalarType, Schema, stored_toward};

/// Which of the two text point formats a [`TextSource`] or [`TextSink`] speaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TextFlavor {
    /// Points only (`.xyz`, `.txt`).
    Xyz,
    /// The point count on its own line, then the points (`.pts`).
    Pts,
}

impl TextFlavor {
    fn format(self) -> Format {
        match self {
            TextFlavor::Xyz => Format::Xyz,
            TextFlavor::Pts => Format::Pts,
        }
    }
}

/// Header information of a text point file that a sink reproduces.
#[derive(Debug, Clone, Default)]
pub struct TextMeta {
    /// Raw comment and blank lines before the first point (PTS: before the count line), with
    /// their terminators.
    pub header: Vec<u8>,
    /// PTS only: raw comment and blank lines between the count line and the first point.
    pub after_count: Vec<u8>,
    /// The separator between columns as the first point line spells it (`" "`, `","`, `", "`…).
    pub separator: String,
    /// Line terminator of the point lines.
    pub eol: LineEnding,
}

/// Text point file content besides the points.
#[derive(Debug, Clone, Default)]
pub struct TextTrailer {
    /// Raw comment and blank lines after the last point.
    pub tail: Vec<u8>,
    /// The last point line ends the file without a line terminator.
    pub unterminated: bool,
}

// ---------------------------------------------------------------------------------------------
// Reader.

/// How the columns of a point line are separated.
#[derive(Debug, Clone, Copy)]
enum Split {
    Whitespace,
    Comma,
}

/// Splits `content` into column tokens.
fn columns(content: &[u8], split: Split, out: &mut Vec<(usize, usize)>) {
    out.clear();
    match split {
        Split::Whitespace => {
            let mut start = None;
            for (i, &c) in content.iter().enumerate() {
                match (c.is_ascii_whitespace(), start) {
                    (false, None) => start = Some(i),
                    (true, Some(s)) => {
                        out.push((s, i));
                        start = None;
                    }
                    _ => {}
                }
            }
            if let Some(s) = start {
                out.push((s, content.len()));
            }
        }
        Split::Comma => {
            let mut s = 0;
            for (i, &c) in content.iter().enumerate() {
                if c == b',' {
                    out.push((s, i));
                    s = i + 1;
                }
            }
            out.push((s, content.len()));
            // A trailing comma does not open a column.
            if let Some(&(a, b)) = out.last()
                && out.len() > 1
                && trim(&content[a..b]).is_empty()
            {
                out.pop();
            }
        }
    }
}

/// Parses one point line into `values`; errors name the line.
fn parse_point(
    path: &Path,
    line: u64,
    content: &[u8],
    split: Split,
    ncols: usize,
    spans: &mut Vec<(usize, usize)>,
    values: &mut Vec<f64>,
) -> Result<(), IoError> {
    columns(content, split, spans);
    if spans.len() != ncols {
        return Err(IoError::invalid(
            path,
            format!(
                "line {line}: {} columns, expected {ncols} like the first point",
                spans.len()
            ),
        ));
    }
    values.clear();
    for (k, &(a, b)) in spans.iter().enumerate() {
        let tok = trim(&content[a..b]);
        let v = parse_f64(tok).ok_or_else(|| {
            IoError::invalid(
                path,
                format!(
                    "line {line}: bad number `{}` in column {}",
                    show(tok),
                    k + 1
                ),
            )
        })?;
        values.push(v);
    }
    Ok(())
}

/// The separator between the first two columns of `content` (leading whitespace trimmed).
fn detect_separator(content: &[u8]) -> Option<(String, Split)> {
    let t = trim(content);
    let is_sep = |c: &u8| c.is_ascii_whitespace() || *c == b',';
    let end = t.iter().position(is_sep)?;
    let len = t[end..].iter().take_while(|c| is_sep(c)).count();
    let sep = &t[end..end + len];
    let split = if sep.contains(&b',') {
        Split::Comma
    } else {
        Split::Whitespace
    };
    Some((String::from_utf8_lossy(sep).into_owned(), split))
}

/// Column names from a header comment like `//X Y Z Intensity` or `# x,y,z,r,g,b`: the last
/// comment line with `n` entries, the first three being x, y and z (any case).
fn names_from_comments(comments: &[&[u8]], n: usize) -> Option<Vec<String>> {
    for raw in comments.iter().rev() {
        let (content, _) = split_eol(raw);
        let t = trim(content);
        let body = if let Some(b) = t.strip_prefix(b"//") {
            b
        } else if let Some(b) = t.strip_prefix(b"#") {
            b
        } else {
            continue;
        };
        let body = String::from_utf8_lossy(body).to_lowercase();
        let names: Vec<String> = if body.contains(',') {
            body.split(',').map(|s| s.trim().to_string()).collect()
        } else {
            body.split_whitespace().map(str::to_string).collect()
        };
        if names.len() != n || names[..3] != ["x", "y", "z"] {
            continue;
        }
        let unique = names
            .iter()
            .enumerate()
            .all(|(i, a)| !a.is_empty() && names[..i].iter().all(|b| b != a));
        if unique {
            return Some(names);
        }
    }
    None
}

/// Streaming reader of `.xyz`, `.txt` and `.pts` point files.
pub struct TextSource {
    info: SourceInfo,
    flavor: TextFlavor,
    lines: LineReader,
    split: Split,
    ncols: usize,
    /// Count declared by a PTS file.
    declared: Option<u64>,
    /// Points delivered so far.
    read: u64,
    /// The first point, parsed at open.
    first: Option<Vec<f64>>,
    /// Comment and blank lines since the last point.
    tail: Vec<u8>,
    /// The last point line had no terminator.
    unterminated: bool,
    exhausted: bool,
    spans: Vec<(usize, usize)>,
    values: Vec<f64>,
    record: Vec<u8>,
}

impl TextSource {
    /// Opens a text point file and reads its header and first point.
    ///
    /// # Errors
    /// Unreadable file, empty file, a PTS file without a count line, a bad first point.
    pub fn open(path: &Path, flavor: TextFlavor) -> Result<TextSource, IoError> {
        TextSource::new(Input::from_path(path)?, flavor)
    }

    /// [`TextSource::open`] on any [`Input`].
    ///
    /// # Errors
    /// As [`TextSource::open`].
    pub fn new(input: Input, flavor: TextFlavor) -> Result<TextSource, IoError> {
        let file_len = input.len();
        let owned = input.name().to_path_buf();
        let path = owned.as_path();
        let mut lines = LineReader::new(input);
        let mut header = Vec::new();
        let mut after_count = Vec::new();
        let mut comment_lines: Vec<Vec<u8>> = Vec::new();
        let mut declared = None;
        let mut first = None;
        let mut eol = LineEnding::Lf;
        let mut separator = String::from(" ");
        let mut split = Split::Whitespace;
        let mut unterminated = false;
        let mut spans = Vec::new();
        let mut values = Vec::new();
        let mut ncols = 3;
        while lines.next_line()? {
            let line = lines.line();
            let raw = lines.raw();
            let (content, _) = split_eol(raw);
            if is_comment_or_blank(content) {
                if declared.is_some() {
                    after_count.extend_from_slice(raw);
                } else {
                    header.extend_from_slice(raw);
                }
                comment_lines.push(raw.to_vec());
                continue;
            }
            if flavor == TextFlavor::Pts && declared.is_none() {
                let t = trim(content);
                let n = parse_u64(t).ok_or_else(|| {
                    IoError::header(
                        path,
                        format!("line {line}: expected the point count, found `{}`", show(t)),
                    )
                })?;
                // A count no file of this size can hold is refused here, naming the file (issue
                // 51: the tiled path's temporary-space check named the temporary directory).
                crate::io::lines::check_text_count(path, (n, "points"), 3, 0, file_len)?;
                declared = Some(n);
                continue;
            }
            // The first point fixes the separator, the column count and the line terminator.
            let Some((sep, sp)) = detect_separator(content) else {
                return Err(IoError::invalid(
                    path,
                    format!("line {line}: a point needs at least 3 columns (x y z), found 1"),
                ));
            };
            columns(content, sp, &mut spans);
            if spans.len() < 3 {
                return Err(IoError::invalid(
                    path,
                    format!(
                        "line {line}: a point needs at least 3 columns (x y z), found {}",
                        spans.len()
                    ),
                ));
            }
            ncols = spans.len();
            parse_point(path, line, content, sp, ncols, &mut spans, &mut values)?;
            separator = sep;
            split = sp;
            eol = LineEnding::of(raw).unwrap_or_default();
            unterminated = LineEnding::of(raw).is_none();
            if declared == Some(0) {
                return Err(IoError::invalid(
                    path,
                    format!("line {line}: more points than the 0 the count line declares"),
                ));
            }
            first = Some(values.clone());
            break;
        }
        if first.is_none() {
            if lines.line() == 0 {
                let what = match flavor {
                    TextFlavor::Pts => "empty file: expected the point count",
                    TextFlavor::Xyz => "empty file: no points",
                };
                return Err(match flavor {
                    TextFlavor::Pts => IoError::header(path, what),
                    TextFlavor::Xyz => IoError::invalid(path, what),
                });
            }
            match (flavor, declared) {
                (TextFlavor::Xyz, _) => return Err(IoError::invalid(path, "no points")),
                (TextFlavor::Pts, None) => {
                    return Err(IoError::header(path, "no point count line"));
                }
                (TextFlavor::Pts, Some(n)) if n > 0 => {
                    return Err(IoError::truncated(
                        path,
                        format!("the count line declares {n} points but the file holds none"),
                    ));
                }
                _ => {}
            }
        }
        let comment_refs: Vec<&[u8]> = comment_lines.iter().map(Vec::as_slice).collect();
        let names =
            names_from_comments(&comment_refs, ncols).unwrap_or_else(|| default_names(ncols, &[]));
        let schema = f64_schema(path, &names)?;
        let meta = TextMeta {
            header,
            after_count,
            separator,
            eol,
        };
        Ok(TextSource {
            info: SourceInfo {
                path: path.to_path_buf(),
                format: flavor.format(),
                schema,
                len: declared,
                faces: None,
                meta: Meta::Text(meta),
            },
            flavor,
            lines,
            split,
            ncols,
            declared,
            read: 0,
            first,
            tail: Vec::new(),
            unterminated,
            exhausted: false,
            spans,
            values,
            record: Vec::new(),
        })
    }

    /// Parses the next point into `self.values`; false when the points are exhausted.
    fn next_point(&mut self) -> Result<bool, IoError> {
        if self.exhausted || self.declared == Some(self.read) {
            return Ok(false);
        }
        if let Some(v) = self.first.take() {
            self.values = v;
            return Ok(true);
        }
        let path = &self.info.path;
        while self.lines.next_line()? {
            let raw = self.lines.raw();
            let (content, _) = split_eol(raw);
            if is_comment_or_blank(content) {
                self.tail.extend_from_slice(raw);
                continue;
            }
            // Comment lines between points are not kept.
            self.tail.clear();
            self.unterminated = LineEnding::of(raw).is_none();
            parse_point(
                path,
                self.lines.line(),
                content,
                self.split,
                self.ncols,
                &mut self.spans,
                &mut self.values,
            )?;
            return Ok(true);
        }
        self.exhausted = true;
        if let Some(n) = self.declared
            && self.read < n
        {
            return Err(IoError::truncated(
                path,
                format!(
                    "the count line declares {n} points but the file holds {}",
                    self.read
                ),
            ));
        }
        Ok(false)
    }
}

impl Source for TextSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn read_batch(&mut self, batch: &mut PointBatch, max: usize) -> Result<usize, IoError> {
        batch.clear(self.read);
        batch.record_len = self.info.schema.record_len;
        let mut n = 0;
        while n < max && self.next_point()? {
            let p = encode_f64_record(&self.values, &mut self.record);
            batch.push(p, &self.record);
            self.read += 1;
            n += 1;
        }
        Ok(n)
    }

    fn finish(mut self: Box<Self>) -> Result<Extras, IoError> {
        // Skip the points the caller did not read.
        while self.next_point()? {
            self.read += 1;
        }
        if self.flavor == TextFlavor::Pts {
            // Only comment lines may follow the declared points.
            while self.lines.next_line()? {
                let raw = self.lines.raw();
                let (content, _) = split_eol(raw);
                if is_comment_or_blank(content) {
                    self.tail.extend_from_slice(raw);
                    continue;
                }
                let line = self.lines.line();
                let n = self.read;
                return Err(if parse_u64(trim(content)).is_some() {
                    IoError::Unsupported {
                        path: self.info.path.clone(),
                        detail: format!(
                            "line {line}: a second point block (several scans in one PTS file)"
                        ),
                    }
                } else {
                    IoError::invalid(
                        &self.info.path,
                        format!("line {line}: more points than the {n} the count line declares"),
                    )
                });
            }
        }
        let unterminated = self.unterminated && self.tail.is_empty();
        Ok(Extras {
            faces: None,
            trailer: Trailer::Text(TextTrailer {
                tail: std::mem::take(&mut self.tail),
                unterminated,
            }),
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Writer.

/// A value a text sink writes that the record does not hold: the noise flag or one of the
/// written normals' values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Column {
    /// The noise flag, `0` or `1`.
    Noise,
    /// A written normal's value.
    Normal(NormalField),
}

impl Column {
    /// The name of the column when it is appended.
    fn name(self) -> &'static str {
        match self {
            Column::Noise => NOISE_FIELD,
            Column::Normal(f) => f.name(NormalNames::Ply),
        }
    }

    /// Appends this column's value for point `i` of `batch` to `line`.
    fn push(self, batch: &PointBatch, i: usize, line: &mut Vec<u8>) {
        match self {
            Column::Noise => line.push(if batch.flag(i) & FLAG_NOISE != 0 {
                b'1'
            } else {
                b'0'
            }),
            Column::Normal(f) => push_value(line, f.ty(), f.value(&batch.normal(i))),
        }
    }
}

/// `header` and `after_count` with `names` appended to the comment line that names the `n`
/// columns (the line [`names_from_comments`] takes the names from), when there is one. The names
/// follow the line's own separator: `, noise` after `//X, Y, Z`, ` noise` after `# x y z`.
fn name_columns(header: &[u8], after_count: &[u8], n: usize, names: &[&str]) -> (Vec<u8>, Vec<u8>) {
    let blobs = [header, after_count];
    let mut found = None;
    for (b, blob) in blobs.iter().enumerate() {
        let mut start = 0;
        for line in blob.split_inclusive(|&c| c == b'\n') {
            if names_from_comments(&[line], n).is_some() {
                found = Some((b, start, start + line.len()));
            }
            start += line.len();
        }
    }
    let mut out = blobs.map(<[u8]>::to_vec);
    if let Some((b, start, end)) = found {
        let (content, eol) = split_eol(&blobs[b][start..end]);
        let body = content.trim_ascii_end().len();
        let sep: &[u8] = match content[..body].iter().rposition(|&c| c == b',') {
            Some(k) => {
                let ws = content[k + 1..body]
                    .iter()
                    .take_while(|c| c.is_ascii_whitespace())
                    .count();
                &content[k..k + 1 + ws]
            }
            None => b" ",
        };
        let mut line = content[..body].to_vec();
        for name in names {
            line.extend_from_slice(sep);
            line.extend_from_slice(name.as_bytes());
        }
        line.extend_from_slice(&content[body..]);
        line.extend_from_slice(eol);
        out[b].splice(start..end, line);
    }
    let [h, a] = out;
    (h, a)
}

/// Streaming writer of `.xyz`, `.txt` and `.pts` point files.
///
/// Like a text source it keeps the header and trailing comments, the separator and the line
/// terminator. For any other layout it writes x, y, z and then every other field of the record,
/// converted field by field, separated by single spaces; an XYZ file then starts with a
/// `# x y z name…` line naming the extra columns. Positions are printed in their field's type when
/// it is a float, and as the shortest text that round-trips the `f64` position otherwise (integer
/// x, y, z such as LAS's scaled `I32` are never rounded to whole units).
pub struct TextSink {
    out: LineSink,
    /// How moved coordinates round to what the output stores ([`SinkOptions::rounding`]).
    rounding: Rounding,
    schema: Schema,
    coords: [ScalarType; 3],
    fields: Vec<usize>,
    separator: String,
    /// Record fields whose column gets another value (a `noise` or `nx` column of an earlier
    /// run).
    overwrite: Vec<(usize, Column)>,
    /// Columns after the record's own.
    append: Vec<Column>,
    tally: Tally,
    line: Vec<u8>,
}

impl TextSink {
    /// Creates a sink that writes `count` points laid out like `like`.
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create(
        path: &Path,
        flavor: TextFlavor,
        like: &SourceInfo,
        count: u64,
    ) -> Result<TextSink, IoError> {
        TextSink::create_with(path, flavor, like, count, &SinkOptions::default())
    }

    /// [`TextSink::create`] with options. With [`SinkOptions::noise_flag`] every point line gets
    /// a last column, 1 for points flagged [`FLAG_NOISE`] and 0 otherwise, after the file's
    /// separator; a header comment naming the columns (`//X Y Z …`, `# x y z …`, or the
    /// `# x y z …` line written for another format) gets the name `noise`. When the columns
    /// already include one named `noise` (a re-run), that column is overwritten instead.
    ///
    /// # Errors
    /// The directory is not writable.
    pub fn create_with(
        path: &Path,
        flavor: TextFlavor,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<TextSink, IoError> {
        TextSink::new(AtomicFile::create(path)?, flavor, like, count, options)
    }

    /// [`TextSink::create_with`] writing to `file` (a file, a stream or memory).
    ///
    /// # Errors
    /// Write failures.
    pub fn new(
        file: AtomicFile,
        flavor: TextFlavor,
        like: &SourceInfo,
        count: u64,
        options: &SinkOptions,
    ) -> Result<TextSink, IoError> {
        let schema = like.schema.clone();
        let fields = extra_fields(&schema);
        let mut wanted: Vec<(Column, Option<usize>)> = Vec::new();
        if options.normals {
            for f in NormalField::ALL {
                wanted.push((Column::Normal(f), f.find(&schema)));
            }
        }
        if options.noise_flag {
            wanted.push((Column::Noise, schema.field_index(NOISE_FIELD)));
        }
        let (mut overwrite, mut append) = (Vec::new(), Vec::new());
        for (c, existing) in wanted {
            match existing {
                Some(i) if fields.contains(&i) => overwrite.push((i, c)),
                _ => append.push(c),
            }
        }
        let names: Vec<&str> = append.iter().map(|c| c.name()).collect();
        let (meta, separator, eol) = match &like.meta {
            Meta::Text(m) => (Some(m), m.separator.clone(), m.eol),
            _ => (None, " ".to_string(), LineEnding::Lf),
        };
        let (header, after_count) = match meta {
            Some(m) if !append.is_empty() => {
                name_columns(&m.header, &m.after_count, schema.fields.len(), &names)
            }
            Some(m) => (m.header.clone(), m.after_count.clone()),
            None => (Vec::new(), Vec::new()),
        };
        let mut out = LineSink::new(file, eol);
        // A body holds the point lines alone.
        if !options.body {
            match meta {
                Some(_) => out.raw(&header)?,
                None if flavor == TextFlavor::Xyz && (!fields.is_empty() || !append.is_empty()) => {
                    let mut h = b"# x y z".to_vec();
                    for &f in &fields {
                        h.push(b' ');
                        h.extend_from_slice(schema.fields[f].name.as_bytes());
                    }
                    for name in &names {
                        h.push(b' ');
                        h.extend_from_slice(name.as_bytes());
                    }
                    out.line(&h)?;
                }
                None => {}
            }
            if flavor == TextFlavor::Pts {
                out.line(count.to_string().as_bytes())?;
            }
            out.raw(&after_count)?;
        }
        Ok(TextSink {
            out,
            rounding: options.rounding,
            coords: coord_types(&schema),
            schema,
            fields,
            separator,
            overwrite,
            append,
            tally: Tally::new(count),
            line: Vec::new(),
        })
    }
}

impl Sink for TextSink {
    fn write_batch(&mut self, batch: &PointBatch) -> Result<(), IoError> {
        check_batch(self.out.path(), &self.schema, batch)?;
        self.tally.add(self.out.path(), batch.len())?;
        let sep = self.separator.as_bytes();
        for (i, p) in batch.positions.iter().enumerate() {
            let rec = batch.record(i);
            self.line.clear();
            // Coordinates print at their field's precision (`f32` ones as `f32`).
            let coords = self.coords;
            let stored = self.rounding.store(
                p.to_array(),
                self.schema.position(rec).to_array(),
                [1.0; 3],
                |k, v, towards| match coords[k] {
                    ScalarType::F32 => stored_toward(v, towards, ScalarType::F32),
                    _ => v,
                },
            );
            for (k, v) in stored.into_iter().enumerate() {
                if k > 0 {
                    self.line.extend_from_slice(sep);
                }
                push_value(&mut self.line, self.coords[k], v);
            }
            for &f in &self.fields {
                self.line.extend_from_slice(sep);
                if let Some(&(_, c)) = self.overwrite.iter().find(|(k, _)| *k == f) {
                    c.push(batch, i, &mut self.line);
                    continue;
                }
                let v = self.schema.get_f64(rec, f);
                push_value(&mut self.line, self.schema.fields[f].ty, v);
            }
            for c in &self.append {
                self.line.extend_from_slice(sep);
                c.push(batch, i, &mut self.line);
            }
            self.out.line(&self.line)?;
        }
        Ok(())
    }

    fn finish(mut self: Box<Self>, extras: &Extras) -> Result<(), IoError> {
        self.tally.check(self.out.path())?;
        let mut unterminated = false;
        if let Trailer::Text(t) = &extras.trailer {
            self.out.raw(&t.tail)?;
            unterminated = t.unterminated;
        }
        self.out.finish(unterminated)
    }

    fn splittable(&self) -> bool {
        true
    }

    fn finish_body(self: Box<Self>) -> Result<BodyStats, IoError> {
        let points = self.tally.written();
        self.out.finish_body()?;
        Ok(BodyStats::count(points))
    }

    fn append_body(&mut self, path: &Path, stats: &BodyStats) -> Result<(), IoError> {
        self.tally.add_body(self.out.path(), stats)?;
        self.out.append_lines(path, stats.points > 0)
    }
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use glam::DVec3;

    use super::*;
    use crate::io::{Cloud, open};

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn separator_and_columns() {
        let (sep, split) = detect_separator(b"  1.5, 2, 3").unwrap();
        assert_eq!(sep, ", ");
        let mut spans = Vec::new();
        columns(b"1.5, 2, 3,", split, &mut spans);
        assert_eq!(spans.len(), 3);
        let (sep, _) = detect_separator(b"1\t2\t3").unwrap();
        assert_eq!(sep, "\t");
        assert!(detect_separator(b"17238").is_none());
    }

    #[test]
    fn names_from_header_comment() {
        let c: [&[u8]; 2] = [b"# scan\n", b"//X Y Z Intensity\n"];
        assert_eq!(
            names_from_comments(&c, 4).unwrap(),
            vec!["x", "y", "z", "intensity"]
        );
        assert!(names_from_comments(&c, 5).is_none());
        let c: [&[u8]; 1] = [b"# a b c d\n"];
        assert!(names_from_comments(&c, 4).is_none());
    }

    #[test]
    fn xyz_roundtrip_is_identical_with_comments_and_commas() {
        let dir = tempfile::tempdir().unwrap();
        let text = "# made by hand\r\n//X,Y,Z,Intensity\r\n1.5,2,-3,0.25\r\n4,5,6,NaN\r\n# end\r\n";
        let p = write(dir.path(), "a.xyz", text);
        let c = Cloud::read(&p, None).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c.info.schema.fields[3].name, "intensity");
        assert_eq!(c.positions[0], DVec3::new(1.5, 2.0, -3.0));
        assert!(c.info.schema.get_f64(&c.records[32..], 3).is_nan());
        let q = dir.path().join("b.xyz");
        c.write(&q, None).unwrap();
        assert_eq!(std::fs::read_to_string(&q).unwrap(), text);
    }

    #[test]
    fn pts_without_final_newline_roundtrips_bytewise() {
        let dir = tempfile::tempdir().unwrap();
        let text = "2\n1 2 3 10 255 0 0\n4 5 6 20 0 255 0";
        let p = write(dir.path(), "a.pts", text);
        let c = Cloud::read(&p, None).unwrap();
        assert_eq!(c.info.len, Some(2));
        assert_eq!(c.info.schema.fields[6].name, "c6");
        let q = dir.path().join("b.pts");
        c.write(&q, None).unwrap();
        assert_eq!(std::fs::read_to_string(&q).unwrap(), text);
    }

    #[test]
    fn pts_count_mismatch() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "a.pts", "3\n1 2 3\n4 5 6\n");
        let e = Cloud::read(&p, None).unwrap_err();
        assert!(matches!(e, IoError::Truncated { .. }), "{e}");
        let p = write(dir.path(), "b.pts", "1\n1 2 3\n4 5 6\n");
        let e = Cloud::read(&p, None).unwrap_err();
        assert!(e.to_string().contains("line 3"), "{e}");
        let p = write(dir.path(), "c.pts", "1\n1 2 3\n1\n4 5 6\n");
        assert!(matches!(
            Cloud::read(&p, None).unwrap_err(),
            IoError::Unsupported { .. }
        ));
        let p = write(dir.path(), "e.pts", "0\n1 2 3\n");
        let e = Cloud::read(&p, None).unwrap_err();
        assert!(e.to_string().contains("line 2: more points"), "{e}");
        let p = write(dir.path(), "f.pts", "# nothing\n0\n");
        assert_eq!(Cloud::read(&p, None).unwrap().len(), 0);
        let p = write(dir.path(), "d.pts", "x\n1 2 3\n");
        assert!(matches!(
            Cloud::read(&p, None).unwrap_err(),
            IoError::Header { .. }
        ));
    }

    #[test]
    fn bad_number_and_ragged_lines_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "a.xyz", "1 2 3\n4 5 6\n7 x 9\n");
        let e = Cloud::read(&p, None).unwrap_err();
        assert!(matches!(e, IoError::Invalid { .. }));
        assert!(
            e.to_string().contains("line 3: bad number `x` in column 2"),
            "{e}"
        );
        let p = write(dir.path(), "b.xyz", "1 2 3\n4 5 6 7\n");
        let e = Cloud::read(&p, None).unwrap_err();
        assert!(e.to_string().contains("line 2: 4 columns"), "{e}");
        let p = write(dir.path(), "c.xyz", "1 2\n");
        assert!(Cloud::read(&p, None).is_err());
    }

    #[test]
    fn streams_in_batches() {
        let dir = tempfile::tempdir().unwrap();
        let mut text = String::new();
        for i in 0..10 {
            text.push_str(&format!("{i} 0 0\n"));
        }
        let p = write(dir.path(), "a.txt", &text);
        let mut src = open(&p, None).unwrap();
        assert_eq!(src.info().len, None);
        let mut b = PointBatch::default();
        assert_eq!(src.read_batch(&mut b, 4).unwrap(), 4);
        assert_eq!(src.read_batch(&mut b, 4).unwrap(), 4);
        assert_eq!(b.start, 4);
        assert_eq!(b.positions[0].x, 4.0);
        assert_eq!(src.read_batch(&mut b, 4).unwrap(), 2);
        assert_eq!(src.read_batch(&mut b, 4).unwrap(), 0);
        src.finish().unwrap();
    }

    #[test]
    fn sink_checks_the_announced_count() {
        let dir = tempfile::tempdir().unwrap();
        let c = Cloud::generated(vec![DVec3::ONE; 3], None, ScalarType::F64);
        let p = dir.path().join("o.pts");
        let mut sink = crate::io::create(&p, None, &c.info, 4).unwrap();
        let mut b = PointBatch::with_capacity(24, 3);
        for (pos, rec) in c.positions.iter().zip(c.records.chunks(24)) {
            b.push(*pos, rec);
        }
        sink.write_batch(&b).unwrap();
        assert!(sink.finish(&c.extras).is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
