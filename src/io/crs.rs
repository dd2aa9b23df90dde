//! The coordinate reference system a file declares, as `lasinfo` and `pdal info` show it.
//!
//! LAS stores its CRS in (E)VLRs of the `LASF_Projection` user: OGC WKT (record 2112, the only
//! form LAS 1.4 point formats 6–10 may use), or GeoTIFF keys (record 34735, the key directory;
//! 34736 its doubles, 34737 its ASCII strings). [`Crs::of`] reads either into one description:
//! the EPSG code of the horizontal (and vertical) system where one is named, the system's name,
//! and the unit of its horizontal axes (metre, foot, US survey foot), which decides what a
//! distance in the file's coordinates means.
//!
//! WKT is read only as far as those three things need: the first `NAME["…"` of the outermost
//! system, its last top-level `AUTHORITY["EPSG","…"]` / `ID["EPSG",…]`, and the `UNIT[…]` (or
//! `LENGTHUNIT[…]`) it states last at its own level (for a projected system, the axes' unit,
//! after the base geographic system's angular one). The WKT itself is kept whole. An E57 file's
//! `coordinateMetadata` is read the same way when it is WKT ([`Crs::of_e57`]).

use super::las::LasVlr;

/// The horizontal unit of a coordinate system's axes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LinearUnit {
    /// The metre (EPSG 9001).
    Metre,
    /// The international foot, 0.3048 m (EPSG 9002).
    Foot,
    /// The US survey foot, 1200/3937 m (EPSG 9003).
    UsSurveyFoot,
    /// Degrees: a geographic system (longitude and latitude, not a length).
    Degree,
}

impl LinearUnit {
    /// The unit's name as shown (`metre`, `foot`, `US survey foot`, `degree`).
    pub fn name(self) -> &'static str {
        match self {
            LinearUnit::Metre => "metre",
            LinearUnit::Foot => "foot",
            LinearUnit::UsSurveyFoot => "US survey foot",
            LinearUnit::Degree => "degree",
        }
    }

    /// The symbol a length in this unit is labelled with (`m`, `ft`, `US ft`, `°`).
    pub fn symbol(self) -> &'static str {
        match self {
            LinearUnit::Metre => "m",
            LinearUnit::Foot => "ft",
            LinearUnit::UsSurveyFoot => "US ft",
            LinearUnit::Degree => "°",
        }
    }

    /// The unit of GeoTIFF's `ProjLinearUnitsGeoKey` / `GeogAngularUnitsGeoKey` code.
    fn of_epsg(code: u16) -> Option<LinearUnit> {
        match code {
            9001 => Some(LinearUnit::Metre),
            9002 => Some(LinearUnit::Foot),
            9003 => Some(LinearUnit::UsSurveyFoot),
            9102 => Some(LinearUnit::Degree),
            _ => None,
        }
    }

    /// The unit a WKT `UNIT["name", factor]` names (by name, else by its factor to metres).
    fn of_wkt(name: &str, factor: Option<f64>) -> Option<LinearUnit> {
        let n = name.to_ascii_lowercase();
        if n.contains("survey") {
            Some(LinearUnit::UsSurveyFoot)
        } else if n.contains("foot") || n.contains("feet") {
            Some(LinearUnit::Foot)
        } else if n == "metre" || n == "meter" || n == "m" {
            Some(LinearUnit::Metre)
        } else if n.contains("degree") {
            Some(LinearUnit::Degree)
        } else {
            match factor {
                Some(f) if (f - 1.0).abs() < 1e-12 => Some(LinearUnit::Metre),
                Some(f) if (f - 0.3048).abs() < 1e-9 => Some(LinearUnit::Foot),
                Some(f) if (f - 1200.0 / 3937.0).abs() < 1e-9 => Some(LinearUnit::UsSurveyFoot),
                _ => None,
            }
        }
    }
}

/// Which record the CRS came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CrsSource {
    /// An OGC WKT record (`LASF_Projection` 2112).
    Wkt,
    /// GeoTIFF keys (`LASF_Projection` 34735).
    GeoTiff,
    /// Free text (an E57 `coordinateMetadata` that is not WKT).
    Text,
}

/// A LAS file's coordinate reference system.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Crs {
    /// The record it was read from.
    pub source: CrsSource,
    /// EPSG code of the horizontal (or compound) system, where one is named.
    pub epsg: Option<u32>,
    /// EPSG code of the vertical system (GeoTIFF `VerticalCSTypeGeoKey`), where one is named.
    pub vertical_epsg: Option<u32>,
    /// The system's name (WKT `NAME`, GeoTIFF citation).
    pub name: Option<String>,
    /// The unit of the horizontal axes.
    pub unit: Option<LinearUnit>,
    /// The WKT, whole (WKT records only).
    pub wkt: Option<String>,
}

/// The `LASF_Projection` user id.
const PROJECTION: &str = "LASF_Projection";

impl Crs {
    /// The CRS the (E)VLRs `vlrs` declare: the WKT record when there is one (LAS 1.4 says it
    /// wins), else the GeoTIFF keys; `None` when neither is there or neither can be read.
    pub fn of<'a>(vlrs: impl IntoIterator<Item = &'a LasVlr>) -> Option<Crs> {
        let vlrs: Vec<&LasVlr> = vlrs
            .into_iter()
            .filter(|v| v.user_id() == PROJECTION)
            .collect();
        let record = |id: u16| vlrs.iter().find(|v| v.record_id() == id).map(|v| v.data());
        if let Some(wkt) = record(2112) {
            let text = String::from_utf8_lossy(wkt);
            let text = text.trim_end_matches('\0').trim();
            if !text.is_empty() {
                return Some(Crs::from_wkt(text));
            }
        }
        record(34735).and_then(|keys| Crs::from_geotiff(keys, record(34736), record(34737)))
    }

    /// The CRS a file declares: a LAS file's (E)VLRs (`meta` and, once read, the `trailer`'s
    /// EVLRs), an E57 file's `coordinateMetadata`; `None` for formats that declare none.
    pub fn of_file(meta: &super::Meta, trailer: Option<&super::Trailer>) -> Option<Crs> {
        match meta {
            super::Meta::Las(m) => {
                let evlrs: Vec<&LasVlr> = match trailer {
                    Some(super::Trailer::Las(t)) => t.evlrs().collect(),
                    _ => Vec::new(),
                };
                Crs::of(m.vlrs().iter().chain(evlrs))
            }
            super::Meta::E57(m) => m.coordinate_metadata().and_then(Crs::of_e57),
            _ => None,
        }
    }

    /// The CRS an E57 file's `coordinateMetadata` states: WKT is read as such, any other text
    /// is kept as the system's name.
    pub fn of_e57(metadata: &str) -> Option<Crs> {
        let text = metadata.trim();
        let wkt = [
            "PROJCS",
            "GEOGCS",
            "GEOCCS",
            "COMPD_CS",
            "PROJCRS",
            "GEOGCRS",
            "GEODCRS",
            "COMPOUNDCRS",
        ]
        .iter()
        .any(|k| text.to_ascii_uppercase().starts_with(k));
        match (wkt, text.is_empty()) {
            (_, true) => None,
            (true, false) => Some(Crs::from_wkt(text)),
            (false, false) => Some(Crs {
                source: CrsSource::Text,
                epsg: None,
                vertical_epsg: None,
                name: Some(text.to_string()),
                unit: None,
                wkt: None,
            }),
        }
    }

    /// The description of a WKT string (WKT 1 or 2).
    pub fn from_wkt(wkt: &str) -> Crs {
        let (name, epsg, unit) = wkt_outline(wkt);
        Crs {
            source: CrsSource::Wkt,
            epsg,
            vertical_epsg: None,
            name,
            unit,
            wkt: Some(wkt.to_string()),
        }
    }

    /// The description of a GeoTIFF key directory (`keys`, little-endian u16s) with its
    /// doubles and ASCII parameters; `None` for a directory too short to hold its header.
    fn from_geotiff(keys: &[u8], _doubles: Option<&[u8]>, ascii: Option<&[u8]>) -> Option<Crs> {
        let words: Vec<u16> = keys
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        let count = usize::from(*words.get(3)?);
        let mut crs = Crs {
            source: CrsSource::GeoTiff,
            epsg: None,
            vertical_epsg: None,
            name: None,
            unit: None,
            wkt: None,
        };
        let mut geographic = None;
        for key in words[4..].chunks_exact(4).take(count) {
            let [id, location, n, value] = [key[0], key[1], key[2], key[3]];
            // Location 0: the value is the key's one short; 34737: an offset into the strings.
            let short = (location == 0).then_some(value);
            match id {
                // GTModelTypeGeoKey: 2 geographic.
                1024 if short == Some(2) => crs.unit = crs.unit.or(Some(LinearUnit::Degree)),
                // GTCitationGeoKey, PCSCitationGeoKey.
                1026 | 3073 if location == 34737 => {
                    let text = ascii.and_then(|a| a.get(usize::from(value)..)).map(|a| {
                        let end = usize::from(n).min(a.len());
                        latin1_or_utf8(&a[..end])
                            .trim_end_matches(['|', '\0'])
                            .to_string()
                    });
                    crs.name = crs.name.or(text.filter(|t| !t.is_empty()));
                }
                // GeographicTypeGeoKey.
                2048 => geographic = short.filter(|&c| c != 0 && c != 32767),
                // ProjectedCSTypeGeoKey.
                3072 => crs.epsg = short.filter(|&c| c != 0 && c != 32767).map(u32::from),
                // ProjLinearUnitsGeoKey.
                3076 => crs.unit = short.and_then(LinearUnit::of_epsg).or(crs.unit),
                // VerticalCSTypeGeoKey.
                4096 => crs.vertical_epsg = short.filter(|&c| c != 0 && c != 32767).map(u32::from),
                _ => {}
            }
        }
        if crs.epsg.is_none() {
            crs.epsg = geographic.map(u32::from);
            if geographic.is_some() {
                crs.unit = crs.unit.or(Some(LinearUnit::Degree));
            }
        }
        Some(crs)
    }

    /// One line: `EPSG:32633 "WGS 84 / UTM zone 33N", metre (WKT)`.
    pub fn summary(&self) -> String {
        let mut parts = Vec::new();
        match (self.epsg, self.vertical_epsg) {
            (Some(h), Some(v)) => parts.push(format!("EPSG:{h}+{v}")),
            (Some(h), None) => parts.push(format!("EPSG:{h}")),
            (None, Some(v)) => parts.push(format!("vertical EPSG:{v}")),
            (None, None) => {}
        }
        if let Some(n) = &self.name {
            parts.push(format!("\"{n}\""));
        }
        let mut s = parts.join(" ");
        if let Some(u) = self.unit {
            if !s.is_empty() {
                s.push_str(", ");
            }
            s.push_str(u.name());
        }
        if s.is_empty() {
            s.push_str("unnamed");
        }
        let from = match self.source {
            CrsSource::Wkt => "WKT",
            CrsSource::GeoTiff => "GeoTIFF keys",
            CrsSource::Text => "text",
        };
        format!("{s} ({from})")
    }
}

/// `b` as UTF-8 when it is, else as ISO 8859-1 (GeoTIFF's ASCII parameters are often Latin-1:
/// `basert på EUREF89`).
fn latin1_or_utf8(b: &[u8]) -> String {
    match std::str::from_utf8(b) {
        Ok(s) => s.to_string(),
        Err(_) => b.iter().map(|&c| char::from(c)).collect(),
    }
}

/// The outermost system's name, its EPSG code and its axes' unit, read from a WKT string.
fn wkt_outline(wkt: &str) -> (Option<String>, Option<u32>, Option<LinearUnit>) {
    // The outermost node's children, at depth 1: its name is its first quoted string; its
    // AUTHORITY/ID and its last UNIT stand at that depth.
    let bytes = wkt.as_bytes();
    let mut depth = 0usize;
    let mut quoted = false;
    let mut name = None;
    let mut epsg = None;
    let mut unit = None;
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if quoted {
            if c == b'"' {
                quoted = false;
            }
            i += 1;
            continue;
        }
        match c {
            b'"' => {
                quoted = true;
                if depth == 1 && name.is_none() {
                    let end = wkt[i + 1..].find('"').map_or(wkt.len(), |e| i + 1 + e);
                    name = Some(wkt[i + 1..end].to_string());
                }
            }
            b'[' | b'(' => depth += 1,
            b']' | b')' => depth = depth.saturating_sub(1),
            _ if depth == 1 && c.is_ascii_alphabetic() => {
                let start = i;
                while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == b'_') {
                    i += 1;
                }
                let keyword = wkt[start..i].to_ascii_uppercase();
                let args = node_args(&wkt[i..]);
                match keyword.as_str() {
                    "AUTHORITY" | "ID" => {
                        if let [auth, code, ..] = &args[..]
                            && auth.eq_ignore_ascii_case("EPSG")
                        {
                            epsg = code.parse().ok().or(epsg);
                        }
                    }
                    "UNIT" | "LENGTHUNIT" | "ANGLEUNIT" => {
                        if let Some(n) = args.first() {
                            let factor = args.get(1).and_then(|f| f.parse().ok());
                            unit = LinearUnit::of_wkt(n, factor).or(unit);
                        }
                    }
                    _ => {}
                }
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    (name, epsg, unit)
}

/// The top-level arguments of the node whose `[…]` starts `rest` (quotes removed), or none
/// when `rest` does not start with a bracket.
fn node_args(rest: &str) -> Vec<String> {
    if !rest.starts_with(['[', '(']) {
        return Vec::new();
    }
    let mut args = Vec::new();
    let mut depth = 0usize;
    let mut quoted = false;
    let mut current = String::new();
    for c in rest.chars() {
        if quoted {
            if c == '"' {
                quoted = false;
            } else {
                current.push(c);
            }
            continue;
        }
        match c {
            '"' => quoted = true,
            '[' | '(' => {
                depth += 1;
                if depth > 1 {
                    current.push(c);
                }
            }
            ']' | ')' => {
                depth -= 1;
                if depth == 0 {
                    args.push(current.trim().to_string());
                    return args;
                }
                current.push(c);
            }
            ',' if depth == 1 => args.push(std::mem::take(&mut current).trim().to_string()),
            _ => current.push(c),
        }
    }
    args
}

#[cfg(test)]
mod tests {
    use super::*;

    const UTM33: &str = r#"PROJCS["WGS 84 / UTM zone 33N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563,AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],AUTHORITY["EPSG","4326"]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",15],UNIT["metre",1,AUTHORITY["EPSG","9001"]],AXIS["Easting",EAST],AXIS["Northing",NORTH],AUTHORITY["EPSG","32633"]]"#;

    #[test]
    fn wkt1_projected_system_names_its_code_and_metres() {
        let c = Crs::from_wkt(UTM33);
        assert_eq!(c.epsg, Some(32633));
        assert_eq!(c.name.as_deref(), Some("WGS 84 / UTM zone 33N"));
        assert_eq!(c.unit, Some(LinearUnit::Metre));
        assert_eq!(
            c.summary(),
            "EPSG:32633 \"WGS 84 / UTM zone 33N\", metre (WKT)"
        );
    }

    #[test]
    fn wkt_in_us_survey_feet_and_wkt2() {
        let feet = r#"PROJCS["NAD83 / Texas Central (ftUS)",GEOGCS["NAD83",UNIT["degree",0.0174532925199433]],UNIT["US survey foot",0.304800609601219],AUTHORITY["EPSG","2277"]]"#;
        let c = Crs::from_wkt(feet);
        assert_eq!(
            (c.epsg, c.unit),
            (Some(2277), Some(LinearUnit::UsSurveyFoot))
        );
        let wkt2 = r#"PROJCRS["ETRS89 / UTM zone 32N",BASEGEOGCRS["ETRS89",ANGLEUNIT["degree",0.0174532925199433]],CS[Cartesian,2],LENGTHUNIT["metre",1],ID["EPSG",25832]]"#;
        let c = Crs::from_wkt(wkt2);
        assert_eq!(c.epsg, Some(25832));
        assert_eq!(c.unit, Some(LinearUnit::Metre));
        assert_eq!(c.name.as_deref(), Some("ETRS89 / UTM zone 32N"));
    }

    #[test]
    fn geotiff_keys_give_the_projected_code_units_and_vertical_code() {
        // Version 1.1.0, 4 keys: model type projected, projected CS 26915, linear units
        // foot, vertical CS 5703.
        let words: [u16; 20] = [
            1, 1, 0, 4, 1024, 0, 1, 1, 3072, 0, 1, 26915, 3076, 0, 1, 9002, 4096, 0, 1, 5703,
        ];
        let keys: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let c = Crs::from_geotiff(&keys, None, None).unwrap();
        assert_eq!(c.epsg, Some(26915));
        assert_eq!(c.vertical_epsg, Some(5703));
        assert_eq!(c.unit, Some(LinearUnit::Foot));
        assert_eq!(c.summary(), "EPSG:26915+5703, foot (GeoTIFF keys)");
        // A geographic system: degrees.
        let words: [u16; 12] = [1, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326];
        let keys: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let c = Crs::from_geotiff(&keys, None, None).unwrap();
        assert_eq!((c.epsg, c.unit), (Some(4326), Some(LinearUnit::Degree)));
        assert!(Crs::from_geotiff(&[1, 0], None, None).is_none());
    }
}
