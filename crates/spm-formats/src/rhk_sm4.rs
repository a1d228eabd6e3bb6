//! RHK Technology `.sm4` reader.
//!
//! Layout (little-endian throughout; from public descriptions of the format): a u16 header
//! size, the UTF-16 signature `STiMage 005.NNN N`, then page count, object count, object field
//! size (12) and two reserved u32, then a list of objects (type, offset, size: three u32). The
//! page index header object (type 1) holds the page count and its own object list; its page
//! index array object (type 2) holds, per page, a 16-byte GUID, data type (0 image, 1 line,
//! …), source, object count, minor version and the page's objects. Each page has a page
//! header (type 3: sizes, scan direction, scales, offsets, period, bias, current, angle, and
//! its own object list, among them the strings, type 10) and page data (type 4: `x_size ·
//! y_size` i32; physical value = raw · z_scale + z_offset).
//!
//! Orientation: a negative `x_scale` means the stored columns run right to left; a positive
//! `y_scale` means the stored lines run bottom to top (both as Gwyddion displays RHK files).
//! Scan direction right is the trace ([`Direction::Forward`]), left the retrace. The stored
//! line order is taken as the acquisition order.
//!
//! Timing: the page header's `period` is the time per data point, in seconds (RHK's SM4
//! description; spym, for one, reads it as `time_per_point`), so a line lasts
//! `period · x_size` and trace + retrace `2 · period · x_size`. The measured graphite file
//! checks the reading: its image pages say 1.953125 ms, i.e. 0.5 s per 256-pixel line (a
//! 4.3-minute frame, usual for atomic resolution at 9 K; per line it would be a 0.5 s frame),
//! and its spectroscopy pages say 0.1 ms for 81-point sweeps, which is plausible only per point.
//! (shared/data/measured/README.md calls 1.953 ms the "line period": it is the pixel period.)

use std::path::Path;

use crate::error::{Ctx, Result};
use crate::model::{Channel, DateTime, Direction, Format, LineTiming, ScanDir, SpmFile};

const OBJECT_BYTES: usize = 12;
const PAGE_HEADER_BYTES: usize = 180;
const MAX_PAGES: u32 = 4096;
const MAX_OBJECTS: u32 = 4096;

const OBJ_PAGE_INDEX_HEADER: u32 = 1;
const OBJ_PAGE_INDEX_ARRAY: u32 = 2;
const OBJ_PAGE_HEADER: u32 = 3;
const OBJ_PAGE_DATA: u32 = 4;
const OBJ_STRING_DATA: u32 = 10;

const STRING_NAMES: &[&str] = &[
    "Label",
    "SystemText",
    "SessionText",
    "UserText",
    "Path",
    "Date",
    "Time",
    "XUnits",
    "YUnits",
    "ZUnits",
    "XLabel",
    "YLabel",
    "StatusChannelText",
    "CompletedLineCount",
    "OverSamplingCount",
    "SlicedVoltage",
    "PLLProStatus",
];

/// Whether `bytes` carry the UTF-16 `STiMage 00` signature at offset 2.
pub(crate) fn has_magic(bytes: &[u8]) -> bool {
    let sig: Vec<u8> = "STiMage 00"
        .encode_utf16()
        .flat_map(|u| u.to_le_bytes())
        .collect();
    bytes.len() >= 2 + sig.len() && bytes[2..2 + sig.len()] == sig[..]
}

/// Reads an RHK `.sm4` file.
pub fn read_sm4(path: impl AsRef<Path>) -> Result<SpmFile> {
    let path = path.as_ref();
    let bytes = crate::read_file(path)?;
    parse(&bytes, path)
}

#[derive(Debug, Clone, Copy)]
struct Object {
    kind: u32,
    offset: usize,
    size: usize,
}

fn read_objects(
    ctx: Ctx<'_>,
    bytes: &[u8],
    at: usize,
    count: u32,
    stride: usize,
    what: &str,
) -> Result<Vec<Object>> {
    if count > MAX_OBJECTS {
        return Err(ctx.too_large(
            format!("{what} object count"),
            u64::from(count),
            u64::from(MAX_OBJECTS),
        ));
    }
    let count = count as usize;
    ctx.slice(bytes, at, count * stride, &format!("{what} object list"))?;
    let mut out = Vec::with_capacity(count);
    for i in 0..count {
        let o = at + i * stride;
        let kind = ctx.u32_le(bytes, o, what)?;
        let offset = ctx.u32_le(bytes, o + 4, what)? as usize;
        let size = ctx.u32_le(bytes, o + 8, what)? as usize;
        if kind != 0 && size > 0 {
            ctx.slice(
                bytes,
                offset,
                size,
                &format!("{what} object of type {kind}"),
            )?;
        }
        out.push(Object { kind, offset, size });
    }
    Ok(out)
}

fn find(objects: &[Object], kind: u32) -> Option<Object> {
    objects
        .iter()
        .copied()
        .find(|o| o.kind == kind && o.size > 0)
}

fn read_strings(
    ctx: Ctx<'_>,
    bytes: &[u8],
    obj: Object,
    count: u16,
    page: usize,
) -> Result<Vec<String>> {
    let end = obj.offset + obj.size;
    let mut p = obj.offset;
    let mut out = Vec::with_capacity(usize::from(count).min(64));
    for i in 0..count {
        if p >= end {
            break;
        }
        let field = format!("page {page} string {i}");
        let len = usize::from(ctx.u16_le(bytes, p, &field)?);
        p += 2;
        if p + 2 * len > end {
            return Err(ctx.truncated(field, p, 2 * len, end - p));
        }
        let units: Vec<u16> = bytes[p..p + 2 * len]
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]))
            .collect();
        let s = String::from_utf16(&units).map_err(|_| ctx.encoding(field, p, "UTF-16LE"))?;
        out.push(s);
        p += 2 * len;
    }
    Ok(out)
}

struct PageHeader {
    string_count: u16,
    page_type: u32,
    x_size: u32,
    y_size: u32,
    scan_dir: u32,
    x_scale: f32,
    y_scale: f32,
    z_scale: f32,
    x_offset: f32,
    y_offset: f32,
    z_offset: f32,
    period: f32,
    bias: f32,
    current: f32,
    angle: f32,
    objects: Vec<Object>,
}

fn read_page_header(ctx: Ctx<'_>, bytes: &[u8], obj: Object, page: usize) -> Result<PageHeader> {
    let what = format!("page {page} header");
    if obj.size < PAGE_HEADER_BYTES {
        return Err(ctx.truncated(what, obj.offset, PAGE_HEADER_BYTES, obj.size));
    }
    let b = obj.offset;
    let u32_at = |o: usize| ctx.u32_le(bytes, b + o, &what);
    let f32_at = |o: usize| ctx.f32_le(bytes, b + o, &what);
    let field_size = usize::from(ctx.u16_le(bytes, b, &what)?);
    if field_size < PAGE_HEADER_BYTES {
        return Err(ctx.invalid(
            format!("{what} field size"),
            format!("{field_size} < {PAGE_HEADER_BYTES}"),
        ));
    }
    let object_count = u32_at(112)?;
    let objects = read_objects(
        ctx,
        bytes,
        b + field_size,
        object_count,
        OBJECT_BYTES,
        &what,
    )?;
    Ok(PageHeader {
        string_count: ctx.u16_le(bytes, b + 2, &what)?,
        page_type: u32_at(4)?,
        x_size: u32_at(24)?,
        y_size: u32_at(28)?,
        scan_dir: u32_at(36)?,
        x_scale: f32_at(56)?,
        y_scale: f32_at(60)?,
        z_scale: f32_at(64)?,
        x_offset: f32_at(72)?,
        y_offset: f32_at(76)?,
        z_offset: f32_at(80)?,
        period: f32_at(84)?,
        bias: f32_at(88)?,
        current: f32_at(92)?,
        angle: f32_at(96)?,
        objects,
    })
}

fn parse_date(date: &str, time: &str) -> Option<DateTime> {
    let d: Vec<&str> = date.trim().split('/').collect();
    let t: Vec<&str> = time.trim().split(':').collect();
    if d.len() != 3 || t.len() < 2 {
        return None;
    }
    let mut year: i32 = d[2].trim().parse().ok()?;
    if year < 100 {
        year += 2000;
    }
    DateTime::new(
        year,
        d[0].trim().parse().ok()?,
        d[1].trim().parse().ok()?,
        t[0].trim().parse().ok()?,
        t[1].trim().parse().ok()?,
        t.get(2)
            .and_then(|s| s.trim().parse::<f64>().ok())
            .unwrap_or(0.0) as u8,
    )
}

/// The page's header entries (`Page{n}.Name`), in the order of the file.
fn push_page_header(
    header: &mut Vec<(String, String)>,
    page: usize,
    data_type: u32,
    ph: &PageHeader,
    strings: &[String],
) {
    let key = |name: &str| format!("Page{page}.{name}");
    header.push((key("DataType"), data_type.to_string()));
    header.push((key("PageType"), ph.page_type.to_string()));
    header.push((key("XSize"), ph.x_size.to_string()));
    header.push((key("YSize"), ph.y_size.to_string()));
    let dir_name = match ph.scan_dir {
        0 => "SCAN_RIGHT",
        1 => "SCAN_LEFT",
        2 => "SCAN_UP",
        3 => "SCAN_DOWN",
        _ => "unknown",
    };
    header.push((key("ScanDirection"), dir_name.to_string()));
    for (name, v) in [
        ("XScale", ph.x_scale),
        ("YScale", ph.y_scale),
        ("ZScale", ph.z_scale),
        ("XOffset", ph.x_offset),
        ("YOffset", ph.y_offset),
        ("ZOffset", ph.z_offset),
        ("Period", ph.period),
        ("Bias", ph.bias),
        ("Current", ph.current),
        ("Angle", ph.angle),
    ] {
        header.push((key(name), format!("{v:e}")));
    }
    for (i, s) in strings.iter().enumerate() {
        let name = STRING_NAMES
            .get(i)
            .map_or_else(|| format!("String{i}"), |n| (*n).to_string());
        header.push((key(&name), s.clone()));
    }
}

/// The image of an image page in display orientation, scaled to its Z unit: (nx, ny, data,
/// whether the slow axis ran upwards).
fn page_image(
    ctx: Ctx<'_>,
    bytes: &[u8],
    page: usize,
    ph: &PageHeader,
    data_obj: Object,
) -> Result<(usize, usize, Vec<f64>, bool)> {
    let key = |name: &str| format!("Page{page}.{name}");
    let (nx, ny) = ctx.check_grid(
        &format!("page {page} x/y size"),
        u64::from(ph.x_size),
        u64::from(ph.y_size),
        1,
        4,
        (data_obj.offset, data_obj.size),
    )?;
    let n = nx * ny;
    if data_obj.size != 4 * n {
        return Err(ctx.invalid_data(
            data_obj.offset,
            format!(
                "page {page} data holds {} bytes, expected {}",
                data_obj.size,
                4 * n
            ),
        ));
    }
    for (name, v) in [
        ("XScale", ph.x_scale),
        ("YScale", ph.y_scale),
        ("ZScale", ph.z_scale),
    ] {
        if !v.is_finite() || v == 0.0 {
            return Err(ctx.invalid(key(name), format!("{v} is not a finite non-zero scale")));
        }
    }
    if !ph.z_offset.is_finite() {
        return Err(ctx.invalid(key("ZOffset"), "not finite"));
    }
    let block = ctx.slice(bytes, data_obj.offset, 4 * n, &format!("page {page} data"))?;
    let (zs, zo) = (f64::from(ph.z_scale), f64::from(ph.z_offset));
    let stored: Vec<f64> = block
        .chunks_exact(4)
        .map(|c| f64::from(i32::from_le_bytes([c[0], c[1], c[2], c[3]])) * zs + zo)
        .collect();
    let mirror_x = ph.x_scale < 0.0;
    let flip_y = ph.y_scale > 0.0;
    let mut data = ctx.vec_with_capacity(n, "page data")?;
    for row in 0..ny {
        let src = if flip_y { ny - 1 - row } else { row };
        let line = &stored[src * nx..(src + 1) * nx];
        if mirror_x {
            data.extend(line.iter().rev());
        } else {
            data.extend_from_slice(line);
        }
    }
    Ok((nx, ny, data, flip_y))
}

/// Parses an RHK `.sm4` file held in memory.
pub(crate) fn parse(bytes: &[u8], path: &Path) -> Result<SpmFile> {
    let ctx = Ctx::new(path);
    if !has_magic(bytes) {
        return Err(ctx.bad_magic(
            Format::RhkSm4,
            "no UTF-16 \"STiMage 00\" signature at byte 2",
        ));
    }
    let header_size = usize::from(ctx.u16_le(bytes, 0, "header size")?);
    if header_size < 36 + 20 {
        return Err(ctx.invalid("header size", format!("{header_size} < 56")));
    }
    let signature_units: Vec<u16> = ctx
        .slice(bytes, 2, 36, "signature")?
        .chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect();
    let signature = String::from_utf16_lossy(&signature_units)
        .trim_end_matches('\0')
        .trim()
        .to_string();
    let object_count = ctx.u32_le(bytes, 42, "file object count")?;
    let stride = ctx.u32_le(bytes, 46, "object field size")? as usize;
    if !(OBJECT_BYTES..=256).contains(&stride) {
        return Err(ctx.invalid("object field size", format!("{stride} (expected 12)")));
    }
    let file_objects = read_objects(
        ctx,
        bytes,
        2 + header_size,
        object_count,
        stride,
        "file header",
    )?;
    let pih = find(&file_objects, OBJ_PAGE_INDEX_HEADER)
        .ok_or_else(|| ctx.missing("page index header object"))?;
    let page_count = ctx.u32_le(bytes, pih.offset, "page index header")?;
    if page_count > MAX_PAGES {
        return Err(ctx.too_large("page count", u64::from(page_count), u64::from(MAX_PAGES)));
    }
    let pih_objects_n = ctx.u32_le(bytes, pih.offset + 4, "page index header")?;
    let pih_objects = read_objects(
        ctx,
        bytes,
        pih.offset + 16,
        pih_objects_n,
        OBJECT_BYTES,
        "page index header",
    )?;
    let pia = find(&pih_objects, OBJ_PAGE_INDEX_ARRAY)
        .ok_or_else(|| ctx.missing("page index array object"))?;

    let mut header = vec![
        ("Signature".to_string(), signature),
        ("PageCount".to_string(), page_count.to_string()),
    ];
    let mut channels = Vec::new();
    let mut recorded = None;
    let mut line_time_s = None;
    let mut entry = pia.offset;
    for page in 0..page_count as usize {
        let what = format!("page {page} index");
        let data_type = ctx.u32_le(bytes, entry + 16, &what)?;
        let n_obj = ctx.u32_le(bytes, entry + 24, &what)?;
        let objects = read_objects(ctx, bytes, entry + 32, n_obj, OBJECT_BYTES, &what)?;
        entry += 32 + OBJECT_BYTES * objects.len();

        let ph_obj = find(&objects, OBJ_PAGE_HEADER)
            .ok_or_else(|| ctx.missing(format!("page {page} header object")))?;
        let ph = read_page_header(ctx, bytes, ph_obj, page)?;
        let strings = match find(&ph.objects, OBJ_STRING_DATA) {
            Some(o) => read_strings(ctx, bytes, o, ph.string_count, page)?,
            None => Vec::new(),
        };
        let string = |i: usize| strings.get(i).map(String::as_str).unwrap_or("");
        let key = |name: &str| format!("Page{page}.{name}");
        push_page_header(&mut header, page, data_type, &ph, &strings);
        if data_type != 0 {
            continue; // spectra and other non-image pages are listed in the header only
        }

        let data_obj = find(&objects, OBJ_PAGE_DATA)
            .ok_or_else(|| ctx.missing(format!("page {page} data object")))?;
        let (nx, ny, data, flip_y) = page_image(ctx, bytes, page, &ph, data_obj)?;
        let direction = if ph.scan_dir == 1 {
            Direction::Backward
        } else {
            Direction::Forward
        };
        let name = match string(0) {
            "" => format!("page {page}"),
            s => s.to_string(),
        };
        let unit = string(9).to_string();
        let size_x_nm = f64::from(ph.x_scale).abs() * nx as f64 * 1e9;
        let size_y_nm = f64::from(ph.y_scale).abs() * ny as f64 * 1e9;
        let mut ch = Channel::new(name, direction, unit, nx, ny, data)
            .map_err(|_| ctx.invalid(key("XSize"), "grid does not match data"))?
            .with_size_nm(size_x_nm, size_y_nm)
            .with_center_nm(f64::from(ph.x_offset) * 1e9, f64::from(ph.y_offset) * 1e9);
        if ph.angle.is_finite() {
            ch = ch.with_angle_deg(f64::from(ph.angle));
        }
        if flip_y {
            ch = ch.with_scan_dir(ScanDir::Up);
        }
        let period = f64::from(ph.period);
        if period.is_finite() && period > 0.0 {
            let line_time = period * nx as f64;
            ch = ch.with_timing(LineTiming {
                line_time_s: line_time,
                line_period_s: 2.0 * line_time,
                first_line_start_s: if direction == Direction::Backward {
                    line_time
                } else {
                    0.0
                },
            });
            line_time_s.get_or_insert(line_time);
        }
        if recorded.is_none() {
            recorded = parse_date(string(5), string(6));
        }
        channels.push(ch);
    }
    if channels.is_empty() {
        return Err(ctx.unsupported("no image pages (only spectra or other page types)"));
    }
    Ok(SpmFile {
        source: path.to_path_buf(),
        format: Format::RhkSm4,
        channels,
        header,
        scan_dir: None,
        line_time_s,
        recorded,
    })
}
