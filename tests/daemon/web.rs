//! The HTTP server for web map clients as a client meets it on the wire: raster-DEM tiles
//! whose pixels are the store's heights at their centres, ETags that change exactly when the
//! data under a tile does, quantized-mesh tiles gzipped once, the documents' fields, tokens,
//! bad requests, and the tile ranges a change event names. (MapLibre and Cesium themselves
//! load the tiles in `web_browser.rs`; GDAL, numpy and the Python and JavaScript
//! quantized-mesh decoders read them in `web_clients.rs`.)

use crate::common;

use common::daemon::*;
use common::http::{get, get_tls, rgba, terrarium, webp_rgba};
use patchwork_core::geom::tiles::{geographic, mercator};
use std::io::Read;

/// A point inside the Copernicus crop only (west of the NASADEM crop), and one inside both.
const COPERNICUS_ONLY: [f64; 2] = [-118.985, 34.53];
const BOTH: [f64; 2] = [-118.94, 34.49];

fn tile_at(z: u32, p: [f64; 2]) -> (u32, u32) {
    let r = mercator::over(z, &patchwork_core::geom::Aabb::new(p[0], p[1], p[0], p[1]));
    (r.x0, r.y0)
}

fn etag(d: &Daemon, path: &str) -> String {
    let r = get(&format!("{}{path}", d.http), &[]);
    assert_eq!(r.status, 200, "{path}: {}", r.text());
    r.header("etag").unwrap().to_string()
}

#[test]
fn raster_tiles_are_the_stores_heights_and_change_exactly_with_its_data() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "cop.tif");
    d.wait("the survey", |s| count(s, "active") == 1);

    let tj = get(&format!("{}/tiles.json", d.http), &[]).json();
    assert_eq!(tj["tileSize"], 256);
    assert_eq!(tj["encoding"], "terrarium");
    // The heights are the store's, measured from its vertical CRS, and both documents say so.
    assert_eq!(tj["heights"], "store");
    let layer = get(&format!("{}/terrain/layer.json", d.http), &[]).json();
    assert_eq!(layer["heights"], "store");
    assert_eq!(layer["vertical_crs"], tj["vertical_crs"]);
    let b: Vec<f64> = serde_json::from_value(tj["bounds"].clone()).unwrap();
    assert!(
        b[0] <= -118.999 && b[2] >= -118.917 && b[1] <= 34.459 && b[3] >= 34.541,
        "{b:?}"
    );
    // One-arc-second cells: 256-pixel tiles are as fine from level 13 on.
    assert_eq!(tj["maxzoom"], 13);
    let template = tj["tiles"][0].as_str().unwrap();
    assert_eq!(
        template,
        format!(
            "{}/tiles/{{z}}/{{x}}/{{y}}.png?encoding=terrarium&size=256",
            d.http
        )
    );

    // Each pixel is the height SampleHeights gives at its centre in EPSG:3857, at the
    // zoom's error; alpha says where there is data.
    let z = 13;
    let (x, y) = tile_at(z, BOTH);
    let path = format!("/tiles/{z}/{x}/{y}.png");
    let r = get(&format!("{}{path}", d.http), &[]);
    assert_eq!(r.status, 200, "{}", r.text());
    assert_eq!(r.header("content-type"), Some("image/png"));
    assert_eq!(r.header("cache-control"), Some("public, max-age=60"));
    assert_eq!(r.header("access-control-allow-origin"), Some("*"));
    let tag = r.header("etag").unwrap().to_string();
    let (w, h, px) = rgba(&r.body);
    assert_eq!((w, h), (256, 256));
    // The same tile as a lossless WebP, under a tag of its own: the same data, and the same
    // heights to the encoding's step (1/256 m). Not always the same bytes: `auto` may
    // resample one request on the GPU and the other on the CPU, which differ by a fraction of
    // a millimetre, enough to round a pixel to its neighbouring step. (That the WebP holds its
    // pixels exactly is `raster::tests::webp_tiles_hold_their_pixels_exactly`.)
    let webp = get(&format!("{}/tiles/{z}/{x}/{y}.webp", d.http), &[]);
    assert_eq!(webp.status, 200, "{}", webp.text());
    assert_eq!(webp.header("content-type"), Some("image/webp"));
    assert_ne!(webp.header("etag"), Some(tag.as_str()));
    let (ww, wh, wpx) = webp_rgba(&webp.body);
    assert_eq!((ww, wh), (256, 256));
    for (a, b) in px.chunks(4).zip(wpx.chunks(4)) {
        assert_eq!(a[3], b[3], "the same pixels have data");
        if a[3] == 255 {
            assert!(
                (terrarium(a) - terrarium(b)).abs() <= 1.0 / 256.0 + 1e-9,
                "{a:?} {b:?}"
            );
        }
    }
    println!(
        "the tile is {} bytes as PNG, {} as WebP",
        r.body.len(),
        webp.body.len()
    );
    let tj_webp = get(&format!("{}/tiles.json?image=webp", d.http), &[]).json();
    assert!(tj_webp["tiles"][0]
        .as_str()
        .unwrap()
        .contains("/tiles/{z}/{x}/{y}.webp?"));
    let roi = mercator::bounds(z, x, y);
    let picks: Vec<(usize, usize)> = (0..16).map(|k| (k * 16 + 3, (k * 37) % 256)).collect();
    let pts: Vec<String> = picks
        .iter()
        .flat_map(|&(i, j)| {
            let px = roi.min[0] + (i as f64 + 0.5) * roi.width() / 256.0;
            let py = roi.max[1] - (j as f64 + 0.5) * roi.height() / 256.0;
            [px.to_string(), py.to_string()]
        })
        .collect();
    let e = mercator::error(z, 256);
    let want = get(
        &format!(
            "{}/heights?crs=EPSG:3857&error={e}&points={}",
            d.http,
            pts.join(",")
        ),
        &[],
    )
    .json();
    let mut valid = 0;
    for (k, &(i, j)) in picks.iter().enumerate() {
        let p = &px[4 * (j * 256 + i)..][..4];
        match want["heights"][k].as_f64() {
            Some(h) => {
                valid += 1;
                assert_eq!(p[3], 255, "pixel {i},{j} has data");
                let got = terrarium(p);
                assert!(
                    (got - h).abs() <= 1.0 / 512.0 + 1e-4,
                    "pixel {i},{j}: {got} against {h}"
                );
            }
            None => assert_eq!(p[3], 0, "pixel {i},{j} has no data"),
        }
    }
    assert!(valid >= 8, "{valid} of the pixels picked have data");

    // The client's copy is still good: 304, no body.
    let again = get(&format!("{}{path}", d.http), &[("If-None-Match", &tag)]);
    assert_eq!(again.status, 304);
    assert!(again.body.is_empty());
    assert_eq!(again.header("etag"), Some(tag.as_str()));
    // Another encoding, size or error is another tile.
    for q in ["?encoding=mapbox", "?size=512", "?error=1"] {
        assert_ne!(etag(&d, &format!("{path}{q}")), tag, "{q}");
    }
    let mapbox = get(&format!("{}{path}?encoding=mapbox", d.http), &[]);
    let (_, _, mpx) = rgba(&mapbox.body);
    for k in (0..256 * 256).step_by(997) {
        let (t, m) = (&px[4 * k..][..4], &mpx[4 * k..][..4]);
        assert_eq!(t[3], m[3]);
        if t[3] == 255 {
            let mh = -10000.0 + (m[0] as f64 * 65536.0 + m[1] as f64 * 256.0 + m[2] as f64) * 0.1;
            assert!((mh - terrarium(t)).abs() <= 0.05 + 1.0 / 512.0 + 1e-6);
        }
    }
    let tif = get(&format!("{}/tiles/{z}/{x}/{y}.tif", d.http), &[]);
    assert_eq!(tif.header("content-type"), Some("image/tiff"));
    assert_eq!(&tif.body[..4], b"II*\0");

    // Far from the data: a transparent tile of the size asked.
    let (fx, fy) = tile_at(z, [0.0, 0.0]);
    for size in [256, 512] {
        let far = get(
            &format!("{}/tiles/{z}/{fx}/{fy}.png?size={size}", d.http),
            &[],
        );
        assert_eq!(far.status, 200);
        let (w, _, fp) = rgba(&far.body);
        assert_eq!(w, size);
        assert!(fp.chunks(4).all(|p| p[3] == 0));
    }
    let far_tag = etag(&d, &format!("/tiles/{z}/{fx}/{fy}.png"));
    let (cx, cy) = tile_at(15, COPERNICUS_ONLY);
    let alone = format!("/tiles/15/{cx}/{cy}.png");
    let alone_tag = etag(&d, &alone);

    // A change event names the tiles it invalidates; the tiles under the new survey change
    // and the others keep their ETags.
    use patchwork::serve::proto::{self as pb, terrain_client::TerrainClient};
    let rt = tokio::runtime::Runtime::new().unwrap();
    let url = d.url.clone();
    let mut events = rt.block_on(async move {
        let mut t = TerrainClient::connect(url).await.unwrap();
        t.subscribe(pb::SubscribeRequest::default())
            .await
            .unwrap()
            .into_inner()
    });
    drop_by_rename(&crop("nasadem_n34w119_crop.tif"), &d.inbox(), "nasa.tif");
    let ev = rt.block_on(async {
        loop {
            let e = tokio::time::timeout(std::time::Duration::from_secs(60), events.message())
                .await
                .expect("an event within a minute")
                .unwrap()
                .unwrap();
            if e.outcome == pb::Outcome::Inserted as i32 {
                return e;
            }
        }
    });
    let c = ev.changed.expect("where the terrain changed");
    assert!(
        c.west <= -118.9666 && c.east >= -118.8837 && c.south <= 34.4364 && c.north >= 34.5194,
        "{c:?}"
    );
    assert!(
        c.west > -118.99,
        "the area is the new survey's, not the whole store: {c:?}"
    );
    assert_eq!(ev.web_tiles.len(), 25);
    assert_eq!(ev.terrain_tiles.len(), 25);
    let r13 = &ev.web_tiles[13];
    assert!(r13.z == 13 && (r13.x0..=r13.x1).contains(&x) && (r13.y0..=r13.y1).contains(&y));
    assert!(!(r13.x0..=r13.x1).contains(&fx));
    d.wait("both surveys", |s| count(s, "active") == 2);
    assert_ne!(
        etag(&d, &path),
        tag,
        "the tile under the new survey changed"
    );
    assert_eq!(etag(&d, &format!("/tiles/{z}/{fx}/{fy}.png")), far_tag);
    let r15 = &ev.web_tiles[15];
    if !(r15.x0..=r15.x1).contains(&cx) {
        assert_eq!(
            etag(&d, &alone),
            alone_tag,
            "a tile the event left out kept its ETag"
        );
    }

    // Bad requests say what is wrong.
    for (bad, code) in [
        ("/tiles/3/8/0.png", 400),
        ("/tiles/25/0/0.png", 400),
        ("/tiles/3/0/x.png", 400),
        ("/tiles/3/0/0.jpg", 404),
        ("/tiles/3/0/0.png?size=300", 400),
        ("/tiles/3/0/0.png?error=-1", 400),
        ("/tiles/3/0/0.png?encoding=jpeg", 400),
        ("/heights?points=1,2,3", 400),
        ("/nothing", 404),
    ] {
        let r = get(&format!("{}{bad}", d.http), &[]);
        assert_eq!(r.status, code, "{bad}: {}", r.text());
        if code == 400 {
            // The kind, for clients to branch on, beside the words.
            let body: serde_json::Value = serde_json::from_slice(&r.body)
                .unwrap_or_else(|e| panic!("{bad}: {e}: {}", r.text()));
            assert_eq!(body["reason"], "INVALID_REQUEST", "{bad}: {body}");
            assert!(!body["error"].as_str().unwrap().is_empty(), "{bad}");
        }
    }
    let long = format!("/heights?points={}", "1,".repeat(10_000));
    assert_eq!(get(&format!("{}{long}", d.http), &[]).status, 414);

    // Tiles run as gRPC requests do, under the same limit on requests at work, and are
    // counted with them.
    let served = || {
        d.json(&["stats", "--json"])["requests_served"]
            .as_u64()
            .unwrap()
    };
    let before = served();
    for k in 0..5 {
        let r = get(
            &format!("{}/tiles/12/{}/{}.png?error={k}", d.http, x / 2, y / 2),
            &[],
        );
        assert_eq!(r.status, 200);
    }
    assert!(served() >= before + 5);
}

#[test]
fn terrain_tiles_are_gzipped_once_and_layer_json_says_where_they_are() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "cop.tif");
    d.wait("the survey", |s| count(s, "active") == 1);

    let layer = get(&format!("{}/terrain/layer.json", d.http), &[]).json();
    assert_eq!(layer["format"], "quantized-mesh-1.0");
    assert_eq!(layer["scheme"], "tms");
    assert_eq!(layer["projection"], "EPSG:4326");
    assert!(layer["tiles"][0]
        .as_str()
        .unwrap()
        .starts_with("{z}/{x}/{y}.terrain?v={version}"));
    assert_eq!(layer["maxzoom"], 12);
    let available = layer["available"].as_array().unwrap();
    assert_eq!(available.len(), 13);
    assert_eq!(
        available[0][0],
        serde_json::json!({"startX": 0, "startY": 0, "endX": 1, "endY": 0})
    );
    let r = geographic::over(
        12,
        &patchwork_core::geom::Aabb::new(BOTH[0], BOTH[1], BOTH[0], BOTH[1]),
    );
    let (x, y) = (r.x0, r.y0);
    let l12 = &available[12];
    assert!(l12.as_array().unwrap().iter().any(|a| {
        a["startX"].as_u64().unwrap() <= x as u64
            && x as u64 <= a["endX"].as_u64().unwrap()
            && a["startY"].as_u64().unwrap() <= y as u64
            && y as u64 <= a["endY"].as_u64().unwrap()
    }));

    let url = format!(
        "{}/terrain/12/{x}/{y}.terrain?v={}",
        d.http,
        layer["version"].as_str().unwrap()
    );
    let all = "application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata";
    let gz = get(&url, &[("Accept", all), ("Accept-Encoding", "gzip")]);
    assert_eq!(gz.status, 200);
    assert!(
        gz.header("vary").is_some_and(|v| v.contains("accept")),
        "{:?}",
        gz.headers
    );
    assert_eq!(
        gz.header("content-type"),
        Some("application/vnd.quantized-mesh")
    );
    assert_eq!(gz.header("content-encoding"), Some("gzip"));
    let mut body = Vec::new();
    flate2::read::GzDecoder::new(&gz.body[..])
        .read_to_end(&mut body)
        .unwrap();
    assert_ne!(&body[..2], &[0x1f, 0x8b], "gzipped once, not twice");
    let raw = get(&url, &[("Accept", all)]);
    assert_eq!(raw.header("content-encoding"), None);
    assert_eq!(raw.body, body, "the same tile, gzipped or not");
    // The header: the heights of the crop (about 300 to 1,200 m), and the ellipsoid's 0 m
    // south of it, where the tile reaches past the survey.
    let f32_at = |o: usize| f32::from_le_bytes(body[o..o + 4].try_into().unwrap());
    let (lo, hi) = (f32_at(24), f32_at(28));
    assert!(lo == 0.0 && 500.0 < hi && hi < 2000.0, "{lo} {hi}");
    // Extensions only when asked for.
    let bare = get(&url, &[]);
    assert!(bare.body.len() < body.len());
    let tag = gz.header("etag").unwrap();
    assert_ne!(bare.header("etag").unwrap(), tag);
    assert_eq!(
        get(&url, &[("Accept", all), ("If-None-Match", tag)]).status,
        304
    );

    // Cesium places heights above the ellipsoid; this crop names no vertical CRS, so its
    // heights cannot be carried there: they come as they are, and every tile says so.
    assert_eq!(layer["heights"], "store");
    let warning = gz.header("warning").expect("a Warning header");
    assert!(
        warning.starts_with("299 patchwork \"") && warning.contains("no vertical CRS"),
        "{warning}"
    );
    let store = get(&format!("{url}&heights=store"), &[("Accept", all)]);
    assert_eq!(store.status, 200);
    assert_eq!(store.header("warning"), None);
    assert_eq!(store.body, body, "the same heights, asked for as they are");
    for bad in ["heights=ellipsoid", "heights=EPSG:4326"] {
        let r = get(&format!("{url}&{bad}"), &[]);
        assert_eq!(r.status, 400, "{bad}");
    }
    let at = format!("points={},{}", BOTH[0], BOTH[1]);
    let h = get(&format!("{}/heights?{at}&heights=ellipsoid", d.http), &[]);
    assert_eq!(h.status, 400);
    assert_eq!(h.json()["reason"], "GEOID", "{}", h.text());
    let h = get(&format!("{}/heights?{at}", d.http), &[]).json();
    assert_eq!(h["vertical_crs"], serde_json::Value::Null);
    assert_eq!(h["frame_error"], 0.0);
    let png = |q: &str| get(&format!("{}/tiles/12/700/1620.png{q}", d.http), &[]);
    assert_eq!(png("?heights=store").header("etag"), png("").header("etag"));
    assert_eq!(png("?heights=feet").status, 400);

    // Both roots exist, whatever the data; out of range is refused.
    for root in ["/terrain/0/0/0.terrain", "/terrain/0/1/0.terrain"] {
        assert_eq!(get(&format!("{}{root}", d.http), &[]).status, 200, "{root}");
    }
    for bad in [
        "/terrain/0/2/0.terrain",
        "/terrain/1/0/2.terrain",
        "/terrain/1/0/0.png",
    ] {
        assert_eq!(get(&format!("{}{bad}", d.http), &[]).status, 400, "{bad}");
    }
    let fp = get(&format!("{}/surveys.geojson", d.http), &[]);
    assert_eq!(fp.header("content-type"), Some("application/geo+json"));
    assert_eq!(fp.json()["features"].as_array().unwrap().len(), 1);
    let page = get(&format!("{}/", d.http), &[]);
    assert!(page
        .header("content-type")
        .unwrap()
        .starts_with("text/html"));
}

#[test]
fn web_tiles_take_the_read_token_in_a_header_or_where_allowed_the_query() {
    const ADMIN: &str = "admin-0123456789abcdef";
    const READ: &str = "read-0123456789abcdef";
    let tmp = tempfile::tempdir().unwrap();
    let tokens = vec![
        ("PATCHWORK_ADMIN_TOKEN".to_string(), ADMIN.to_string()),
        ("PATCHWORK_READ_TOKEN".to_string(), READ.to_string()),
    ];
    let mut env = tokens.clone();
    env.push((
        "PATCHWORK_PUBLIC_URL".into(),
        "https://terrain.example.org/".into(),
    ));
    let d = Daemon::start_with(
        tmp.path(),
        Setup {
            env,
            client_env: vec![("PATCHWORK_TOKEN".into(), ADMIN.into())],
            ..Setup::default()
        },
    );
    let tile = format!("{}/tiles/3/1/3.png", d.http);
    let bearer = format!("Bearer {READ}");
    let r = get(&tile, &[]);
    assert_eq!(r.status, 401);
    assert_eq!(r.header("www-authenticate"), Some("Bearer"));
    assert_eq!(
        get(&tile, &[("Authorization", "Bearer wrong-0123456789abcdef")]).status,
        401
    );
    let opened = get(&tile, &[("Authorization", &bearer)]);
    assert_eq!(opened.status, 200);
    // What a token opened is no shared cache's to keep.
    assert_eq!(opened.header("cache-control"), Some("private, max-age=60"));
    assert_eq!(get(&format!("{tile}?token={READ}"), &[]).status, 200);
    assert_eq!(get(&format!("{tile}?token={ADMIN}"), &[]).status, 200);
    // The page and its libraries hold no data; documents hand the token on.
    assert_eq!(get(&format!("{}/", d.http), &[]).status, 200);
    // TileJSON's absolute URLs name the configured public URL, with the token.
    let tj = get(&format!("{}/tiles.json?token={READ}", d.http), &[]).json();
    let url = tj["tiles"][0].as_str().unwrap();
    assert!(
        url.starts_with("https://terrain.example.org/tiles/{z}/")
            && url.ends_with(&format!("&token={READ}")),
        "{url}"
    );
    let layer = get(&format!("{}/terrain/layer.json?token={READ}", d.http), &[]).json();
    assert!(layer["tiles"][0]
        .as_str()
        .unwrap()
        .ends_with(&format!("&token={READ}")));
    drop(d);

    // With query tokens turned off, only the header opens.
    let cfg = tmp.path().join("no-query-token.toml");
    std::fs::write(&cfg, "[http]\nquery_token = false\n").unwrap();
    let tmp2 = tempfile::tempdir().unwrap();
    let mut env = tokens;
    env.push((
        "PATCHWORK_CONFIG".into(),
        cfg.to_string_lossy().into_owned(),
    ));
    let d = Daemon::start_with(
        tmp2.path(),
        Setup {
            env,
            client_env: vec![("PATCHWORK_TOKEN".into(), ADMIN.into())],
            ..Setup::default()
        },
    );
    let tile = format!("{}/tiles/3/1/3.png", d.http);
    assert_eq!(get(&format!("{tile}?token={READ}"), &[]).status, 401);
    assert_eq!(get(&tile, &[("Authorization", &bearer)]).status, 200);
    // Nor do the documents put a token into the URLs they hand out.
    let tj = get(
        &format!("{}/tiles.json?token={READ}", d.http),
        &[("Authorization", &bearer)],
    )
    .json();
    assert!(!tj["tiles"][0].as_str().unwrap().contains("token"), "{tj}");
}

#[test]
fn a_daemon_with_a_certificate_serves_web_clients_over_tls_only() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start_with(
        tmp.path(),
        Setup {
            tls: true,
            ..Setup::default()
        },
    );
    let https = d.http.replace("http://127.0.0.1", "https://localhost");
    let r = get_tls(
        &format!("{https}/tiles/3/1/3.png"),
        &tls_file("ca.pem"),
        &[],
    );
    assert_eq!(r.status, 200);
    assert_eq!(r.header("content-type"), Some("image/png"));
    // Plain HTTP on the same port gets no answer.
    let plain = std::net::TcpStream::connect(d.http.trim_start_matches("http://")).unwrap();
    plain
        .set_read_timeout(Some(std::time::Duration::from_secs(15)))
        .unwrap();
    let mut plain = plain;
    use std::io::Write;
    plain
        .write_all(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        .unwrap();
    let mut back = Vec::new();
    let _ = plain.read_to_end(&mut back);
    assert!(!back.starts_with(b"HTTP/1.1 200"), "plain HTTP was served");
}

#[test]
fn heights_tiles_and_documents_name_the_surveys_that_served_them() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    // The sidecar first, so that the survey is read with it.
    std::fs::write(
        d.inbox().join("cop.tif.toml"),
        "title = \"Copernicus DEM GLO-30\"\nlicense = \"Copernicus DEM licence\"\n\
         attribution = \"© DLR, © Airbus, Copernicus\"\nacquired = \"2011-01/2015-01\"\n",
    )
    .unwrap();
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "cop.tif");
    drop_by_rename(&crop("nasadem_n34w119_crop.tif"), &d.inbox(), "nas.tif");
    d.wait("both surveys", |s| count(s, "active") == 2);

    let listed = d.surveys();
    let cop = listed
        .iter()
        .find(|s| s["source"].as_str().unwrap().ends_with("cop.tif"))
        .unwrap();
    assert_eq!(cop["title"], "Copernicus DEM GLO-30");
    assert_eq!(cop["acquired"], "2011-01/2015-01");
    let nas = listed
        .iter()
        .find(|s| s["source"].as_str().unwrap().ends_with("nas.tif"))
        .unwrap();
    assert_eq!(nas["title"], serde_json::Value::Null);

    let at = format!(
        "points={},{},{},{},0,0",
        COPERNICUS_ONLY[0], COPERNICUS_ONLY[1], BOTH[0], BOTH[1]
    );
    let h = get(&format!("{}/heights?{at}&sources=true", d.http), &[]).json();
    let sources = h["sources"].as_array().unwrap();
    assert_eq!(sources.len(), 3);
    assert_eq!(sources[0]["file"], "cop.tif");
    assert_eq!(sources[0]["title"], "Copernicus DEM GLO-30");
    assert_eq!(sources[0]["license"], "Copernicus DEM licence");
    assert_eq!(sources[0]["id"], cop["id"]);
    assert!(sources[0]["cell_m"].as_f64().unwrap() > 20.0);
    assert!(sources[1].is_object());
    assert_eq!(sources[2], serde_json::Value::Null, "no height, no source");
    let plain = get(&format!("{}/heights?{at}", d.http), &[]).json();
    assert_eq!(plain["heights"], h["heights"]);
    assert!(plain.get("sources").is_none());

    // A tile over both crops: each survey with its share of the samples.
    let (x, y) = tile_at(12, BOTH);
    let s = get(&format!("{}/tiles/12/{x}/{y}/sources.json", d.http), &[]);
    assert_eq!(s.status, 200, "{}", s.text());
    let s = s.json();
    let list = s["sources"].as_array().unwrap();
    assert_eq!(list.len(), 2, "{s:#}");
    let total: f64 = list.iter().map(|v| v["share"].as_f64().unwrap()).sum();
    assert!((total - 1.0).abs() < 1e-9, "{s:#}");
    let samples: u64 = list.iter().map(|v| v["samples"].as_u64().unwrap()).sum();
    assert_eq!(samples, s["samples"].as_u64().unwrap());
    assert!(samples > 0 && samples <= 256 * 256);
    assert_eq!(
        get(&format!("{}/tiles/12/{x}/{y}/other.json", d.http), &[]).status,
        404
    );

    // The documents credit what their area shows.
    let tj = get(&format!("{}/tiles.json", d.http), &[]).json();
    assert_eq!(tj["attribution"], "© DLR, © Airbus, Copernicus");
    let away = get(&format!("{}/tiles.json?bounds=10,10,11,11", d.http), &[]).json();
    assert_eq!(away["attribution"], "");
    let bad = get(&format!("{}/tiles.json?bounds=10,10,11", d.http), &[]);
    assert_eq!(bad.status, 400);
    let layer = get(&format!("{}/terrain/layer.json", d.http), &[]).json();
    assert_eq!(layer["attribution"], "© DLR, © Airbus, Copernicus");
    let fp = get(&format!("{}/surveys.geojson", d.http), &[]).json();
    let files: Vec<&str> = fp["features"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["properties"]["file"].as_str().unwrap())
        .collect();
    assert!(
        files.contains(&"cop.tif") && files.contains(&"nas.tif"),
        "{files:?}"
    );

    // The CLI says the same.
    let p = format!("{},{}", COPERNICUS_ONLY[0], COPERNICUS_ONLY[1]);
    let v = d.json(&["sample", "--points", &p, "--sources", "--json"]);
    assert_eq!(v[0]["source"]["title"], "Copernicus DEM GLO-30");
    assert_eq!(v[0]["source"]["survey"], cop["id"]);
}

/// A quantized-mesh tile's vertices (u, v in 0..=32767) and, where the tile has them, its
/// oct-encoded normals, one a vertex.
fn quantized_vertices(body: &[u8]) -> (Vec<[u32; 2]>, Option<Vec<[u8; 2]>>) {
    let u32_at = |o: usize| u32::from_le_bytes(body[o..o + 4].try_into().unwrap());
    let u16_at = |o: usize| u16::from_le_bytes(body[o..o + 2].try_into().unwrap());
    let n = u32_at(88) as usize;
    let mut o = 92;
    let mut axes = [vec![0u32; n], vec![0u32; n]];
    for axis in &mut axes {
        let mut v = 0i32;
        for x in axis.iter_mut() {
            let z = u16_at(o) as i32;
            o += 2;
            v += (z >> 1) ^ -(z & 1);
            *x = v as u32;
        }
    }
    o += 2 * n; // heights
    let wide = n > 65_536;
    let size = if wide { 4 } else { 2 };
    o = o.div_ceil(size) * size;
    let triangles = u32_at(o) as usize;
    o += 4 + 3 * triangles * size;
    for _ in 0..4 {
        let k = u32_at(o) as usize;
        o += 4 + k * size;
    }
    let mut normals = None;
    while o + 5 <= body.len() {
        let (id, len) = (body[o], u32_at(o + 1) as usize);
        let data = &body[o + 5..o + 5 + len];
        if id == 1 {
            normals = Some(data.chunks(2).map(|c| [c[0], c[1]]).collect());
        }
        o += 5 + len;
    }
    let vertices = (0..n).map(|k| [axes[0][k], axes[1][k]]).collect();
    (vertices, normals)
}

/// An oct-encoded normal as a unit vector.
fn oct_decode([a, b]: [u8; 2]) -> [f64; 3] {
    let f = |v: u8| v as f64 / 255.0 * 2.0 - 1.0;
    let (x, y) = (f(a), f(b));
    let z = 1.0 - x.abs() - y.abs();
    let (x, y) = if z < 0.0 {
        ((1.0 - y.abs()) * x.signum(), (1.0 - x.abs()) * y.signum())
    } else {
        (x, y)
    };
    let l = (x * x + y * y + z * z).sqrt();
    [x / l, y / l, z / l]
}

#[test]
fn terrain_normals_agree_across_tile_edges() {
    let tmp = tempfile::tempdir().unwrap();
    let d = Daemon::start(tmp.path());
    drop_by_rename(&crop("copernicus_n34w119_crop.tif"), &d.inbox(), "cop.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    let all = "application/vnd.quantized-mesh;extensions=octvertexnormals-watermask-metadata";
    let r = geographic::over(
        13,
        &patchwork_core::geom::Aabb::new(BOTH[0], BOTH[1], BOTH[0], BOTH[1]),
    );
    let (x, y) = (r.x0, r.y0);
    let tile = |x: u32, y: u32| {
        let t = get(
            &format!("{}/terrain/13/{x}/{y}.terrain", d.http),
            &[("Accept", all)],
        );
        assert_eq!(t.status, 200);
        quantized_vertices(&t.body)
    };
    // West–east and south–north neighbours: the shared edge's vertices, and their normals.
    let mut worst = 0.0f64;
    let mut shared = 0;
    for ((ax, ay), (bx, by), vertical) in [((x, y), (x + 1, y), true), ((x, y), (x, y + 1), false)]
    {
        let (va, na) = tile(ax, ay);
        let (vb, nb) = tile(bx, by);
        let (na, nb) = (na.expect("normals"), nb.expect("normals"));
        for (i, p) in va.iter().enumerate() {
            // On a's east (or north) edge, the vertex of b's west (or south) edge.
            let (edge, along) = if vertical { (p[0], p[1]) } else { (p[1], p[0]) };
            if edge != 32767 {
                continue;
            }
            let Some(j) = vb.iter().position(|q| {
                let (e, a) = if vertical { (q[0], q[1]) } else { (q[1], q[0]) };
                e == 0 && a == along
            }) else {
                continue;
            };
            shared += 1;
            let (a, b) = (oct_decode(na[i]), oct_decode(nb[j]));
            let cos = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0);
            worst = worst.max(cos.acos().to_degrees());
        }
    }
    println!("{shared} shared edge vertices, normals at most {worst:.2}° apart");
    assert!(shared > 100, "{shared}");
    // Both tiles work the normal out from the same heights around the vertex; what is left
    // is the 8-bit oct encoding's rounding.
    assert!(worst < 1.5, "normals {worst:.2}° apart across an edge");
}

#[test]
fn a_projected_store_serves_the_whole_web_pyramid_and_both_cesium_roots() {
    let tmp = tempfile::tempdir().unwrap();
    let setup = Setup {
        env: vec![("PATCHWORK_CRS".into(), "EPSG:32631".into())],
        ..Setup::default()
    };
    let d = Daemon::start_with(tmp.path(), setup);
    drop_by_rename(&crop("real/ventoux_utm31.tif"), &d.inbox(), "ventoux.tif");
    d.wait("the survey", |s| count(s, "active") == 1);
    // Mont Ventoux, inside the UTM crop.
    let p = [5.2786, 44.174];
    // Every zoom's tile over it, though a UTM zone's CRS reaches only part of the low ones:
    // the rest of those tiles is nodata, not a refusal of the whole tile.
    for z in 0..=14 {
        let (x, y) = tile_at(z, p);
        let r = get(&format!("{}/tiles/{z}/{x}/{y}.png", d.http), &[]);
        assert_eq!(r.status, 200, "zoom {z}: {}", r.text());
    }
    for root in ["/terrain/0/0/0.terrain", "/terrain/0/1/0.terrain"] {
        let r = get(&format!("{}{root}", d.http), &[]);
        assert_eq!(r.status, 200, "{root}: {}", r.text());
    }
    for z in 1..=12 {
        let r = geographic::over(z, &patchwork_core::geom::Aabb::new(p[0], p[1], p[0], p[1]));
        let url = format!("{}/terrain/{z}/{}/{}.terrain", d.http, r.x0, r.y0);
        assert_eq!(get(&url, &[]).status, 200, "{url}");
    }
    // Where the data is, a tile's pixel is its height: the pixel holding the summit against
    // /heights at the pixel's centre.
    let z = 13;
    let (x, y) = tile_at(z, p);
    let (w, _, px) = rgba(&get(&format!("{}/tiles/{z}/{x}/{y}.png", d.http), &[]).body);
    let b = mercator::bounds(z, x, y);
    let [mx, my] = mercator::project(p[0], p[1]);
    let (i, j) = (
        ((mx - b.min[0]) / b.width() * w as f64) as usize,
        ((b.max[1] - my) / b.height() * w as f64) as usize,
    );
    let k = 4 * (j * w as usize + i);
    assert_eq!(px[k + 3], 255, "no data at the summit's pixel");
    let centre = mercator::unproject(
        b.min[0] + (i as f64 + 0.5) / w as f64 * b.width(),
        b.max[1] - (j as f64 + 0.5) / w as f64 * b.height(),
    );
    let e = mercator::error(z, 256);
    let h = get(
        &format!(
            "{}/heights?points={},{}&error={e}",
            d.http, centre[0], centre[1]
        ),
        &[],
    )
    .json();
    let want = h["heights"][0].as_f64().unwrap();
    let got = terrarium(&px[k..k + 4]);
    assert!((got - want).abs() < 0.01, "{got} against /heights' {want}");
    assert!(want > 1500.0, "{want}: not the summit");
}
