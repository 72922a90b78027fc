//! Bearer tokens. The admin token opens every call; the read token, when one is set, opens the
//! Terrain service only; with no read token, Terrain is open to all, but for Subscribe, whose
//! events name files and their errors as the Admin listing does. Health and reflection are
//! always open, so that load balancers and tools can find the daemon.
//!
//! Tokens are compared by their BLAKE3 hashes, whose equality is constant-time, so the time a
//! refusal takes says nothing about how much of a guess was right.

use patchwork_engine::config::Config;
use tonic::service::Interceptor;
use tonic::{Request, Status};

/// What one service lets in.
#[derive(Clone)]
pub struct Gate {
    /// Hashes of the tokens that open this service; empty opens it to all.
    accept: Vec<blake3::Hash>,
    /// A token that is valid, but not here: refused with PERMISSION_DENIED, which tells its
    /// holder what is wrong.
    elsewhere: Option<blake3::Hash>,
    service: &'static str,
}

fn hash(t: &patchwork_engine::config::Secret) -> blake3::Hash {
    blake3::hash(t.expose().as_bytes())
}

impl Gate {
    /// The gate of the Admin service: the admin token, when there is one.
    pub fn admin(cfg: &Config) -> Gate {
        Gate {
            accept: cfg.admin_token.iter().map(hash).collect(),
            elsewhere: cfg.read_token.as_ref().map(hash),
            service: "Admin",
        }
    }

    /// The gate of the Terrain service: open unless a read token is set, and then that token
    /// or the admin token.
    pub fn terrain(cfg: &Config) -> Gate {
        let accept = match &cfg.read_token {
            None => Vec::new(),
            Some(r) => std::iter::once(r)
                .chain(&cfg.admin_token)
                .map(hash)
                .collect(),
        };
        Gate {
            accept,
            elsewhere: None,
            service: "Terrain",
        }
    }

    /// Whether every call gets in: no token is set for this service.
    pub fn is_open(&self) -> bool {
        self.accept.is_empty()
    }

    /// Checks an `authorization` header's value against this gate.
    pub fn check(&self, header: Option<&str>) -> Result<(), Status> {
        if self.is_open() {
            return Ok(());
        }
        // The scheme is case-insensitive (RFC 7235 §2.1), the token is not, and is taken as
        // sent: a token with a space more is another token.
        let token = header
            .and_then(|h| h.split_once(' '))
            .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
            .map(|(_, t)| t.trim_start_matches(' '));
        let Some(token) = token else {
            return Err(Status::unauthenticated(format!(
                "{} calls need a token: send the header \"authorization: Bearer <token>\" \
                 (the CLI reads PATCHWORK_TOKEN or --token-file)",
                self.service
            )));
        };
        let h = blake3::hash(token.as_bytes());
        // Every accepted hash is compared, whichever matches, to keep the time the same.
        let ok = self.accept.iter().fold(false, |ok, a| ok | (*a == h));
        if ok {
            Ok(())
        } else if self.elsewhere == Some(h) {
            Err(Status::permission_denied(format!(
                "the read token does not open {} calls: use the admin token",
                self.service
            )))
        } else {
            Err(Status::unauthenticated(format!(
                "the token is not valid for {} calls",
                self.service
            )))
        }
    }
}

impl Gate {
    /// Checks a request's token against this gate.
    pub fn admit<T>(&self, req: &Request<T>) -> Result<(), Status> {
        let header = req
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok());
        self.check(header)
    }
}

impl Interceptor for Gate {
    fn call(&mut self, req: Request<()>) -> Result<Request<()>, Status> {
        self.admit(&req)?;
        Ok(req)
    }
}

/// Whether `listen` only reaches this machine: every address it resolves to is loopback.
pub fn is_loopback(listen: &str) -> bool {
    use std::net::ToSocketAddrs;
    match listen.to_socket_addrs() {
        Ok(addrs) => {
            let addrs: Vec<_> = addrs.collect();
            !addrs.is_empty() && addrs.iter().all(|a| a.ip().is_loopback())
        }
        Err(_) => false,
    }
}

/// Refuses to expose the Admin service beyond this machine without a token.
pub fn check_exposure(cfg: &Config) -> Result<(), String> {
    if cfg.admin_token.is_none() && !is_loopback(&cfg.listen) {
        return Err(format!(
            "listen = {} reaches beyond this machine, but no admin token is set, so anyone \
             who can reach the port could ingest, retire and compact: set \
             PATCHWORK_ADMIN_TOKEN (or admin_token in the config; `openssl rand -hex 32` makes \
             one), or listen on 127.0.0.1",
            cfg.listen
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use patchwork_engine::config::Secret;
    use tonic::Code;

    fn cfg(admin: Option<&str>, read: Option<&str>) -> Config {
        Config {
            admin_token: admin.map(|t| Secret(t.into())),
            read_token: read.map(|t| Secret(t.into())),
            ..Config::default()
        }
    }

    const ADMIN: &str = "admin-token-0123456789";
    const READ: &str = "read-token-0123456789";

    fn code(g: &Gate, header: Option<&str>) -> Option<Code> {
        g.check(header).err().map(|s| s.code())
    }

    #[test]
    fn tokens_open_what_they_should_and_nothing_else() {
        let c = cfg(Some(ADMIN), None);
        let (admin, terrain) = (Gate::admin(&c), Gate::terrain(&c));
        let bearer = |t: &str| format!("Bearer {t}");
        assert_eq!(code(&admin, Some(&bearer(ADMIN))), None);
        assert_eq!(code(&admin, None), Some(Code::Unauthenticated));
        assert_eq!(
            code(&admin, Some(&bearer("admin-token-0123456788"))),
            Some(Code::Unauthenticated)
        );
        assert_eq!(code(&admin, Some(ADMIN)), Some(Code::Unauthenticated));
        assert!(terrain.is_open(), "reads are open without a read token");
        assert_eq!(code(&terrain, None), None);

        let c = cfg(Some(ADMIN), Some(READ));
        let (admin, terrain) = (Gate::admin(&c), Gate::terrain(&c));
        assert_eq!(code(&terrain, Some(&bearer(READ))), None);
        assert_eq!(code(&terrain, Some(&bearer(ADMIN))), None);
        assert_eq!(code(&terrain, None), Some(Code::Unauthenticated));
        assert_eq!(
            code(&admin, Some(&bearer(READ))),
            Some(Code::PermissionDenied)
        );
        assert!(Gate::admin(&cfg(None, None)).is_open());
    }

    #[test]
    fn the_scheme_is_any_case_and_the_token_exact() {
        let admin = Gate::admin(&cfg(Some(ADMIN), None));
        for scheme in ["Bearer", "bearer", "BEARER", "bEaReR"] {
            assert_eq!(code(&admin, Some(&format!("{scheme} {ADMIN}"))), None);
        }
        assert_eq!(code(&admin, Some(&format!("Bearer  {ADMIN}"))), None);
        for wrong in [
            format!("Bearer {ADMIN} "),
            format!("Bearer {ADMIN}\t"),
            format!("Bearer {}", ADMIN.to_uppercase()),
            format!("Basic {ADMIN}"),
            format!("Bearer{ADMIN}"),
        ] {
            assert_eq!(
                code(&admin, Some(&wrong)),
                Some(Code::Unauthenticated),
                "{wrong:?}"
            );
        }
    }

    #[test]
    fn exposure_beyond_loopback_needs_an_admin_token() {
        let mut c = cfg(None, None);
        for l in ["127.0.0.1:50051", "[::1]:50051", "localhost:50051"] {
            c.listen = l.into();
            assert!(check_exposure(&c).is_ok(), "{l}");
        }
        c.listen = "0.0.0.0:50051".into();
        let e = check_exposure(&c).unwrap_err();
        assert!(
            e.contains("PATCHWORK_ADMIN_TOKEN") && e.contains("0.0.0.0"),
            "{e}"
        );
        c.admin_token = Some(Secret(ADMIN.into()));
        assert!(check_exposure(&c).is_ok());
    }
}
