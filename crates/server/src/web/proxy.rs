//! A proxy's routes to replicas of regions (`serve --follow URL --region ...`): an nginx
//! config, printed by `patchwork proxy-config`, that sends each web tile to the replica whose
//! region holds the whole tile, and everything else (tiles across a border, points, the
//! pyramids' descriptions, the viewer) to a replica of the whole store.
//!
//! nginx matches a request's path against regular expressions, so each level's columns and
//! rows inside a region become a pattern of numbers (`(?:1[2-9]|2[0-3])` for 12..=23): one
//! line a level, a pyramid and a region, whatever the number of tiles.

use patchwork_core::geom::tiles::{geographic, mercator, TileRange, MAX_LEVEL};
use patchwork_core::geom::Aabb;
use std::fmt::Write;

/// A replica of one region, as the proxy reaches it.
#[derive(Clone, Debug, PartialEq)]
pub struct RegionRoute {
    /// The upstream's name in the config: letters, digits and `_`.
    pub name: String,
    /// Where the replica's HTTP server listens: `host:port`.
    pub addr: String,
    /// The longitudes and latitudes (degrees) whose tiles go to it: the replica's region for
    /// a store in EPSG:4326; in another CRS, a box whose every point the region holds.
    pub lonlat: Aabb,
}

impl RegionRoute {
    /// Parses `NAME=http://HOST:PORT@WEST,SOUTH,EAST,NORTH`.
    pub fn parse(text: &str) -> Result<RegionRoute, String> {
        let bad = |why: &str| format!("--replica {text}: {why}");
        let (name, rest) = text
            .split_once('=')
            .ok_or_else(|| bad("expected NAME=http://HOST:PORT@WEST,SOUTH,EAST,NORTH"))?;
        let (url, bounds) = rest
            .rsplit_once('@')
            .ok_or_else(|| bad("expected @WEST,SOUTH,EAST,NORTH after the URL"))?;
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            return Err(bad("a name is letters, digits and _"));
        }
        let v: Vec<f64> = bounds
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad("the bounds are four numbers"))?;
        let [w, s, e, n]: [f64; 4] = v
            .try_into()
            .map_err(|_| bad("the bounds are four numbers"))?;
        if !(-180.0..=180.0).contains(&w)
            || !(-180.0..=180.0).contains(&e)
            || !(-90.0..=90.0).contains(&s)
            || !(-90.0..=90.0).contains(&n)
            || w >= e
            || s >= n
        {
            return Err(bad(
                "expected WEST < EAST in [-180, 180] and SOUTH < NORTH in [-90, 90], degrees",
            ));
        }
        Ok(RegionRoute {
            name: name.to_string(),
            addr: upstream_addr(url).map_err(|why| bad(&why))?,
            lonlat: Aabb::new(w, s, e, n),
        })
    }
}

/// `host:port` of an `http://host:port` URL.
pub fn upstream_addr(url: &str) -> Result<String, String> {
    let rest = url
        .strip_prefix("http://")
        .ok_or_else(|| format!("{url}: expected http://HOST:PORT (the replica's HTTP server)"))?;
    let addr = rest.trim_end_matches('/');
    match addr.rsplit_once(':') {
        Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok() => {
            Ok(addr.to_string())
        }
        _ => Err(format!("{url}: expected http://HOST:PORT")),
    }
}

/// The nginx config (what goes in its `http` block) of a proxy listening on `listen` in front
/// of `whole` (`host:port`, a replica of the whole store or the writer) and the replicas of
/// `regions`, routing tiles of levels up to `max_level`.
pub fn nginx(listen: &str, whole: &str, regions: &[RegionRoute], max_level: u32) -> String {
    let max_level = max_level.min(MAX_LEVEL);
    let mut out = String::new();
    let _ = writeln!(
        out,
        "# Patchwork: web tiles routed to the replicas of their regions; everything else, and a\n\
         # tile no one region holds whole, to the replica of the whole store. In nginx's `http`\n\
         # block (e.g. /etc/nginx/conf.d/patchwork.conf). Written by `patchwork proxy-config`."
    );
    let _ = writeln!(out, "map $uri $patchwork_upstream {{");
    let _ = writeln!(out, "    default patchwork_whole;");
    // The raster-DEM pyramid, then Cesium's: their paths and the tiles of a level in a box.
    type Within = fn(u32, &Aabb) -> Option<TileRange>;
    let pyramids: [(&str, &str, Within); 2] = [
        ("tiles", "[a-z]+", mercator::within),
        ("terrain", "terrain", geographic::within),
    ];
    for r in regions {
        for z in 0..=max_level {
            for (path, ext, within) in pyramids {
                if let Some(t) = within(z, &r.lonlat) {
                    let _ = writeln!(
                        out,
                        "    \"~^/{path}/{z}/{}/{}\\.{ext}$\" patchwork_{};",
                        range_pattern(t.x0, t.x1),
                        range_pattern(t.y0, t.y1),
                        r.name
                    );
                }
            }
        }
    }
    let _ = writeln!(out, "}}\n");
    let upstream = |out: &mut String, name: &str, addr: &str| {
        let _ = writeln!(
            out,
            "upstream patchwork_{name} {{\n    server {addr};\n    keepalive 16;\n}}\n"
        );
    };
    upstream(&mut out, "whole", whole);
    for r in regions {
        upstream(&mut out, &r.name, &r.addr);
    }
    let _ = writeln!(
        out,
        "server {{\n    listen {listen};\n    location / {{\n        \
         proxy_pass http://$patchwork_upstream;\n        \
         proxy_http_version 1.1;\n        \
         proxy_set_header Connection \"\";\n        \
         proxy_set_header Host $host;\n    }}\n}}"
    );
    out
}

/// A regular expression matching exactly the decimal numbers `lo..=hi` (no leading zeros).
pub fn range_pattern(lo: u32, hi: u32) -> String {
    let mut parts = Vec::new();
    let mut from = lo as u64;
    let hi = hi as u64;
    // One run of numbers of each length.
    while from <= hi {
        let digits = from.to_string().len() as u32;
        let top = (10u64.pow(digits) - 1).min(hi);
        same_length(&from.to_string(), &top.to_string(), &mut parts);
        from = top + 1;
    }
    format!("(?:{})", parts.join("|"))
}

/// Patterns for the numbers from `lo` to `hi`, both of the same number of digits.
fn same_length(lo: &str, hi: &str, out: &mut Vec<String>) {
    if lo == hi {
        out.push(lo.to_string());
        return;
    }
    let n = lo.len() - 1;
    let (a, b) = (lo.as_bytes()[0] - b'0', hi.as_bytes()[0] - b'0');
    let (lo_rest, hi_rest) = (&lo[1..], &hi[1..]);
    let any = |k: usize| {
        if k == 0 {
            String::new()
        } else {
            format!("[0-9]{{{k}}}")
        }
    };
    let digits = |x: u8, y: u8| {
        if x == y {
            x.to_string()
        } else {
            format!("[{x}-{y}]")
        }
    };
    if a == b {
        let mut inner = Vec::new();
        same_length(lo_rest, hi_rest, &mut inner);
        out.extend(inner.into_iter().map(|p| format!("{a}{p}")));
        return;
    }
    let (low_full, high_full) = (
        lo_rest.bytes().all(|c| c == b'0'),
        hi_rest.bytes().all(|c| c == b'9'),
    );
    // The first digit's numbers, unless all of them are in.
    let first = if low_full { a } else { a + 1 };
    let last = if high_full { b } else { b - 1 };
    if !low_full {
        let mut inner = Vec::new();
        same_length(lo_rest, &"9".repeat(n), &mut inner);
        out.extend(inner.into_iter().map(|p| format!("{a}{p}")));
    }
    if first <= last {
        out.push(format!("{}{}", digits(first, last), any(n)));
    }
    if !high_full {
        let mut inner = Vec::new();
        same_length(&"0".repeat(n), hi_rest, &mut inner);
        out.extend(inner.into_iter().map(|p| format!("{b}{p}")));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whether `pattern` (as `range_pattern` writes it) matches `s` in full: a small matcher
    /// for the forms it writes, alternatives of digits, classes and counted classes.
    fn matches(pattern: &str, s: &str) -> bool {
        let body = pattern
            .strip_prefix("(?:")
            .and_then(|p| p.strip_suffix(')'))
            .unwrap();
        body.split('|').any(|alt| one(alt.as_bytes(), s.as_bytes()))
    }

    fn one(p: &[u8], s: &[u8]) -> bool {
        if p.is_empty() {
            return s.is_empty();
        }
        let (set, rest): (Box<dyn Fn(u8) -> bool>, &[u8]) = if p[0] == b'[' {
            let (lo, hi) = (p[1], p[3]);
            (Box::new(move |c| (lo..=hi).contains(&c)), &p[5..])
        } else {
            let d = p[0];
            (Box::new(move |c| c == d), &p[1..])
        };
        let (count, rest) = if rest.first() == Some(&b'{') {
            let end = rest.iter().position(|&c| c == b'}').unwrap();
            let k: usize = std::str::from_utf8(&rest[1..end]).unwrap().parse().unwrap();
            (k, &rest[end + 1..])
        } else {
            (1, rest)
        };
        s.len() >= count && s[..count].iter().all(|&c| set(c)) && one(rest, &s[count..])
    }

    #[test]
    fn a_range_pattern_matches_its_numbers_and_no_others() {
        let mut h = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move |m: u64| {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            h % m
        };
        let mut cases = vec![
            (0, 0),
            (0, 9),
            (5, 5),
            (9, 10),
            (10, 99),
            (12, 23),
            (0, 16_777_215),
        ];
        for _ in 0..300 {
            let scale = [10, 100, 1000, 100_000, 16_777_216][next(5) as usize];
            let a = next(scale) as u32;
            let b = next(scale) as u32;
            cases.push((a.min(b), a.max(b)));
        }
        for (lo, hi) in cases {
            let p = range_pattern(lo, hi);
            let probes = [
                lo.saturating_sub(1),
                lo,
                lo + 1,
                (lo + hi) / 2,
                hi.saturating_sub(1),
                hi,
                hi + 1,
                hi * 10 + 3,
                next(20_000_000) as u32,
            ];
            for x in probes {
                let want = (lo..=hi).contains(&x);
                assert_eq!(matches(&p, &x.to_string()), want, "{x} in {lo}..={hi}: {p}");
            }
            // No leading zeros are taken.
            assert!(!matches(&p, &format!("0{lo}")), "{p}");
        }
    }

    #[test]
    fn a_replica_is_named_with_its_address_and_box() {
        let r = RegionRoute::parse("west=http://127.0.0.1:8101@-180,-90,-118.95,90").unwrap();
        assert_eq!(r.name, "west");
        assert_eq!(r.addr, "127.0.0.1:8101");
        assert_eq!(r.lonlat, Aabb::new(-180.0, -90.0, -118.95, 90.0));
        for bad in [
            "west=127.0.0.1:8101@-180,-90,0,90",
            "we st=http://h:1@-180,-90,0,90",
            "west=http://h:1@0,-90,-10,90",
            "west=http://h:1@-180,-90,0",
            "west=http://h:1",
        ] {
            assert!(RegionRoute::parse(bad).is_err(), "{bad}");
        }
        let half = RegionRoute::parse("west=http://127.0.0.1:8101@-180,-90,0,90").unwrap();
        let conf = nginx("8080", "127.0.0.1:8001", &[half], 24);
        assert!(conf.contains("upstream patchwork_west"), "{conf}");
        assert!(
            conf.contains("\"~^/tiles/1/(?:0)/(?:[0-1])\\.[a-z]+$\" patchwork_west;"),
            "{conf}"
        );
        assert!(
            conf.contains("\"~^/terrain/0/(?:0)/(?:0)\\.terrain$\" patchwork_west;"),
            "{conf}"
        );
    }
}
