//! libpq's password sources for a PostgreSQL URL without a password (issue 25): the
//! README recommended `~/.pgpass`, but the client ignored it, so the password had to go on
//! the command line, where `ps` shows it.
//!
//! As libpq does, in this order, for a connection whose URL gives no password:
//! 1. `PGPASSWORD`;
//! 2. the password file `PGPASSFILE`, else `~/.pgpass` (`$HOME/.pgpass`): lines
//!    `hostname:port:database:username:password`, `#` comment lines, `*` matching anything
//!    in the first four fields, `\:` and `\\` escaping a colon and a backslash, the first
//!    matching line wins. A socket folder (or no host) matches `localhost`, a missing port
//!    5432, a missing database the user name. The file is ignored, with a warning, unless it
//!    is a regular file with no group or world access (mode 0600 or less), as libpq does.
//!
//! Limit: with several hosts in the URL, the entry is looked up for the first.

use std::path::{Path, PathBuf};

/// The fields of one password-file line, unescaped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Entry {
    pub host: String,
    pub port: String,
    pub database: String,
    pub user: String,
    pub password: String,
}

/// What a connection is looked up by.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Target<'a> {
    pub host: &'a str,
    pub port: u16,
    pub database: &'a str,
    pub user: &'a str,
}

/// Splits one line into its five fields (`\:` and `\\` unescaped; the password is the rest
/// of the line); `None` for a comment, a blank line or a line with fewer than five fields.
pub(crate) fn parse_line(line: &str) -> Option<Entry> {
    let line = line.trim_end_matches(['\r', '\n']);
    if line.is_empty() || line.starts_with('#') {
        return None;
    }
    let mut fields = vec![String::new()];
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        match c {
            '\\' => {
                if let Some(next) = chars.next() {
                    fields.last_mut()?.push(next);
                }
            }
            ':' if fields.len() < 5 => fields.push(String::new()),
            _ => fields.last_mut()?.push(c),
        }
    }
    let [host, port, database, user, password]: [String; 5] = fields.try_into().ok()?;
    Some(Entry {
        host,
        port,
        database,
        user,
        password,
    })
}

fn field_matches(field: &str, value: &str) -> bool {
    field == "*" || field == value
}

/// The password of the first line of `text` that matches `target`.
pub(crate) fn lookup(text: &str, target: &Target<'_>) -> Option<String> {
    let port = target.port.to_string();
    text.lines().filter_map(parse_line).find_map(|e| {
        (field_matches(&e.host, target.host)
            && field_matches(&e.port, &port)
            && field_matches(&e.database, target.database)
            && field_matches(&e.user, target.user))
        .then_some(e.password)
    })
}

/// Why a password file is not used, `None` when it may be: it must be a regular file and,
/// on Unix, grant nothing to group or others.
pub(crate) fn refused(meta: &std::fs::Metadata) -> Option<&'static str> {
    if !meta.is_file() {
        return Some("it is not a regular file");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        if meta.permissions().mode() & 0o077 != 0 {
            return Some("it has group or world access; permissions should be u=rw (0600) or less");
        }
    }
    None
}

/// The password file: `PGPASSFILE`, else `$HOME/.pgpass`.
fn passfile(env: &dyn Fn(&str) -> Option<String>) -> Option<PathBuf> {
    env("PGPASSFILE")
        .filter(|p| !p.is_empty())
        .map(PathBuf::from)
        .or_else(|| env("HOME").map(|h| Path::new(&h).join(".pgpass")))
}

/// The password for `target` from `PGPASSWORD` or the password file, with the environment
/// read through `env`.
pub(crate) fn password(
    env: &dyn Fn(&str) -> Option<String>,
    target: &Target<'_>,
) -> Option<String> {
    if let Some(p) = env("PGPASSWORD").filter(|p| !p.is_empty()) {
        return Some(p);
    }
    let file = passfile(env)?;
    let meta = std::fs::metadata(&file).ok()?;
    if let Some(why) = refused(&meta) {
        tracing::warn!(file = %file.display(), "password file ignored: {why}");
        return None;
    }
    let text = std::fs::read_to_string(&file)
        .inspect_err(
            |e| tracing::warn!(file = %file.display(), error = %e, "password file unreadable"),
        )
        .ok()?;
    lookup(&text, target)
}

/// Sets the password of a configuration that has none from libpq's sources (the process
/// environment and the password file).
pub(crate) fn fill_in(config: &mut postgres::Config) {
    if config.get_password().is_some() {
        return;
    }
    let Some(user) = config.get_user().map(str::to_owned) else {
        return;
    };
    let host = match config.get_hosts().first() {
        Some(postgres::config::Host::Tcp(h)) => h.clone(),
        // A socket folder, as libpq: matched as `localhost`.
        _ => "localhost".to_owned(),
    };
    let port = config.get_ports().first().copied().unwrap_or(5432);
    let database = config.get_dbname().unwrap_or(&user).to_owned();
    let env = |name: &str| std::env::var(name).ok();
    let target = Target {
        host: &host,
        port,
        database: &database,
        user: &user,
    };
    if let Some(p) = password(&env, &target) {
        config.password(p);
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn entry(f: [&str; 5]) -> Entry {
        Entry {
            host: f[0].into(),
            port: f[1].into(),
            database: f[2].into(),
            user: f[3].into(),
            password: f[4].into(),
        }
    }

    #[test]
    fn lines_parse_with_escapes_and_comments() {
        let cases: &[(&str, Option<[&str; 5]>)] = &[
            (
                "db:5432:cdb:lab:secret",
                Some(["db", "5432", "cdb", "lab", "secret"]),
            ),
            ("*:*:*:*:pw", Some(["*", "*", "*", "*", "pw"])),
            // The password is the rest of the line: unescaped colons belong to it.
            ("h:1:d:u:a:b:c", Some(["h", "1", "d", "u", "a:b:c"])),
            (r"h\:v6:1:d:u:p\:w", Some(["h:v6", "1", "d", "u", "p:w"])),
            (r"h:1:d\\x:u:p\\", Some(["h", "1", r"d\x", "u", r"p\"])),
            (r"h:1:d:u\:x:pw", Some(["h", "1", "d", "u:x", "pw"])),
            ("h:1:d:u:pw\r", Some(["h", "1", "d", "u", "pw"])),
            ("h:1:d:u:", Some(["h", "1", "d", "u", ""])),
            ("# h:1:d:u:pw", None),
            ("", None),
            ("h:1:d:u", None),
            (r"h:1:d:u\:pw", None),
        ];
        for (line, want) in cases {
            assert_eq!(parse_line(line), want.map(entry), "line {line:?}");
        }
    }

    #[test]
    fn the_first_matching_line_wins_and_stars_match_anything() {
        let file = "\
# lab database
db.lab:5432:cdb:lab:first
db.lab:*:cdb:lab:second
*:5433:*:lab:third
localhost:5432:*:*:local
*:*:*:admin:any\\:thing
";
        let t = |host, port, database, user| Target {
            host,
            port,
            database,
            user,
        };
        let cases: &[(Target<'_>, Option<&str>)] = &[
            (t("db.lab", 5432, "cdb", "lab"), Some("first")),
            (t("db.lab", 6000, "cdb", "lab"), Some("second")),
            (t("other", 5433, "x", "lab"), Some("third")),
            (t("localhost", 5432, "x", "bob"), Some("local")),
            (t("anywhere", 1, "db", "admin"), Some("any:thing")),
            (t("db.lab", 5432, "other", "lab"), None),
            (t("db.lab", 5432, "cdb", "eve"), None),
            // `*` in the file is a wildcard; `*` asked for is a name like any other.
            (t("*", 5432, "cdb", "lab"), None),
        ];
        for (target, want) in cases {
            assert_eq!(lookup(file, target).as_deref(), *want, "target {target:?}");
        }
    }

    #[test]
    fn sources_in_libpq_order_and_a_file_others_can_read_is_ignored() {
        let dir = std::env::temp_dir().join(format!("spm-cdb-pgpass-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("pgpass");
        std::fs::write(&file, "*:*:*:lab:from-file\n").unwrap();
        let target = Target {
            host: "db",
            port: 5432,
            database: "cdb",
            user: "lab",
        };
        let set_mode = |mode: u32| {
            #[cfg(unix)]
            {
                use std::os::unix::fs::PermissionsExt;
                std::fs::set_permissions(&file, std::fs::Permissions::from_mode(mode)).unwrap();
            }
        };
        let file_text = file.display().to_string();
        let home = dir.display().to_string();
        let env = |pgpassword: Option<&str>, pgpassfile: Option<&str>| {
            let (pw, pf, home) = (
                pgpassword.map(str::to_owned),
                pgpassfile.map(str::to_owned),
                home.clone(),
            );
            move |name: &str| match name {
                "PGPASSWORD" => pw.clone(),
                "PGPASSFILE" => pf.clone(),
                "HOME" => Some(home.clone()),
                _ => None,
            }
        };
        set_mode(0o600);
        let cases: &[(Option<&str>, Option<&str>, Option<&str>)] = &[
            (Some("from-env"), Some(&file_text), Some("from-env")),
            (None, Some(&file_text), Some("from-file")),
            (Some(""), Some(&file_text), Some("from-file")),
            // No PGPASSFILE: $HOME/.pgpass, absent here.
            (None, None, None),
            (None, Some("/nonexistent/pgpass"), None),
        ];
        for (pw, pf, want) in cases {
            assert_eq!(
                password(&env(*pw, *pf), &target).as_deref(),
                *want,
                "PGPASSWORD {pw:?} PGPASSFILE {pf:?}"
            );
        }
        std::fs::copy(&file, dir.join(".pgpass")).unwrap();
        set_mode(0o600);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(dir.join(".pgpass"), std::fs::Permissions::from_mode(0o600))
                .unwrap();
        }
        assert_eq!(
            password(&env(None, None), &target).as_deref(),
            Some("from-file"),
            "~/.pgpass"
        );
        #[cfg(unix)]
        for mode in [0o640, 0o604, 0o644, 0o660] {
            set_mode(mode);
            assert_eq!(
                password(&env(None, Some(&file_text)), &target),
                None,
                "mode {mode:o} must be ignored"
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
