//! deploy/ (issue 24.8): the sysusers.d and tmpfiles.d files create the user, groups and
//! directories the systemd units use, and the units parse. Checked twice: by reading the
//! files (always), and by installing them into a scratch root with systemd's own tools —
//! `systemd-sysusers --root`, `systemd-tmpfiles --root --create`, `systemd-analyze verify
//! --root` — where those tools are installed (else the test prints why it skipped that part).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn deploy() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy")
}

/// Every unit: file name → (key → values) of its [Service] section (and the others).
fn units() -> Vec<(String, HashMap<String, Vec<String>>)> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(deploy().join("systemd")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "service") {
            let text = std::fs::read_to_string(&p).unwrap().replace("\\\n", " ");
            let mut keys: HashMap<String, Vec<String>> = HashMap::new();
            for l in text.lines().map(str::trim).filter(|l| !l.starts_with('#') && l.contains('=')) {
                let (k, v) = l.split_once('=').unwrap();
                keys.entry(k.trim().to_string()).or_default().push(v.trim().to_string());
            }
            out.push((p.file_name().unwrap().to_string_lossy().into_owned(), keys));
        }
    }
    assert!(out.len() >= 2, "the units of deploy/systemd");
    out
}

/// The non-comment lines of a configuration file, split into fields (quoted fields kept).
fn entries(path: &Path) -> Vec<Vec<String>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(|l| {
            let mut f = Vec::new();
            let mut rest = l;
            while !rest.is_empty() {
                rest = rest.trim_start();
                if let Some(r) = rest.strip_prefix('"') {
                    let end = r.find('"').unwrap();
                    f.push(r[..end].to_string());
                    rest = &r[end + 1..];
                } else {
                    let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
                    f.push(rest[..end].to_string());
                    rest = &rest[end..];
                }
            }
            f
        })
        .collect()
}

#[test]
fn sysusers_and_tmpfiles_declare_what_the_units_use() {
    let users = entries(&deploy().join("sysusers.d/cncgw.conf"));
    let dirs = entries(&deploy().join("tmpfiles.d/cncgw.conf"));
    let user_exists = |u: &str| users.iter().any(|e| e[0] == "u" && e[1] == u);
    // `u NAME` makes the group NAME too; `g NAME` a group; `m USER GROUP` a membership.
    let group_exists = |g: &str| users.iter().any(|e| (e[0] == "u" || e[0] == "g") && e[1] == g);
    let member = |u: &str, g: &str| users.iter().any(|e| e[0] == "m" && e[1] == u && e[2] == g);
    let dir = |p: &str| dirs.iter().find(|e| e[0] == "d" && e[1] == p).cloned();
    let mut checked = 0;
    for (name, k) in units() {
        let Some(user) = k.get("User").and_then(|v| v.first()) else { continue };
        assert!(user_exists(user), "{name}: User={user} is not created by sysusers.d/cncgw.conf");
        let group = &k["Group"][0];
        assert!(group_exists(group), "{name}: Group={group} is not created");
        for g in k.get("SupplementaryGroups").into_iter().flatten().flat_map(|v| v.split_whitespace()) {
            assert!(member(user, g), "{name}: {user} is not made a member of {g}");
        }
        // Where the service writes (its state) and reads (its programs): directories created
        // with the service's user as owner.
        let state = k["Environment"].iter().find_map(|e| e.strip_prefix("CNCGW_STATE_DIR=")).expect("the unit sets CNCGW_STATE_DIR");
        let program = k["ExecStart"][0].split_whitespace().last().unwrap();
        let programs = Path::new(program).parent().unwrap().to_str().unwrap();
        for p in [state, programs] {
            let d = dir(p).unwrap_or_else(|| panic!("{name}: {p} is not created by tmpfiles.d/cncgw.conf"));
            assert_eq!((&d[3], &d[4]), (user, group), "{name}: {p} must belong to {user}:{group}");
            let mode = u32::from_str_radix(&d[2], 8).unwrap();
            assert_eq!(mode & 0o700, 0o700, "{name}: {user} must read, write and enter {p}");
            // Every parent up to /var/lib is created too (the service must be able to enter it).
            let mut up = Path::new(p).parent();
            while let Some(q) = up.filter(|q| q.starts_with("/var/lib/cncgw")) {
                assert!(dir(q.to_str().unwrap()).is_some(), "{name}: the parent {} is not created", q.display());
                up = q.parent();
            }
        }
        checked += 1;
    }
    assert!(checked >= 1, "a unit with User= (cncgw-run@.service)");
}

fn have(tool: &str) -> bool {
    Command::new(tool).arg("--version").output().is_ok_and(|o| o.status.success())
}

/// A `d` line's owner in a scratch root: systemd-tmpfiles 252 resolves user names on the
/// host, not in `--root`, so the names are replaced by the ids sysusers gave in the root.
fn ids_of(root: &Path) -> HashMap<String, String> {
    let mut ids = HashMap::new();
    for (file, id_field) in [("etc/passwd", 2), ("etc/group", 2)] {
        for l in std::fs::read_to_string(root.join(file)).unwrap().lines() {
            let f: Vec<&str> = l.split(':').collect();
            ids.entry(f[0].to_string()).or_insert_with(|| f[id_field].to_string());
        }
    }
    ids
}

#[test]
fn installs_into_a_scratch_root_and_the_units_verify() {
    let missing: Vec<&str> = ["systemd-sysusers", "systemd-tmpfiles", "systemd-analyze"].into_iter().filter(|t| !have(t)).collect();
    if !missing.is_empty() {
        // In CI a skip would pass off an unrun check as run: scripts/install-test-deps.sh
        // installs systemd, so a missing tool there is a failure.
        assert!(std::env::var("CI").as_deref() != Ok("true"), "{} not installed: run scripts/install-test-deps.sh", missing.join(", "));
        println!("SKIPPED: {} not installed (apt-get install systemd); only the file check ran", missing.join(", "));
        return;
    }
    let root = tempfile::tempdir().unwrap();
    let r = root.path();
    // A fresh system's account files (Debian: dialout is gid 20).
    std::fs::create_dir_all(r.join("etc")).unwrap();
    std::fs::write(r.join("etc/passwd"), "root:x:0:0:root:/root:/bin/sh\n").unwrap();
    std::fs::write(r.join("etc/group"), "root:x:0:\ndialout:x:20:\n").unwrap();
    let o = Command::new("systemd-sysusers").arg(format!("--root={}", r.display())).arg(deploy().join("sysusers.d/cncgw.conf")).output().unwrap();
    assert!(o.status.success(), "systemd-sysusers: {}", String::from_utf8_lossy(&o.stderr));
    let passwd = std::fs::read_to_string(r.join("etc/passwd")).unwrap();
    let cncgw = passwd.lines().find(|l| l.starts_with("cncgw:")).expect("the user cncgw is created");
    assert!(cncgw.ends_with(":/var/lib/cncgw:/usr/sbin/nologin"), "{cncgw}");
    let group = std::fs::read_to_string(r.join("etc/group")).unwrap();
    assert!(group.lines().any(|l| l.starts_with("dialout:") && l.ends_with("cncgw")), "{group}");

    if unsafe { libc::geteuid() } != 0 {
        println!("SKIPPED: systemd-tmpfiles --create needs root to give the directories their owner; sysusers and verify ran");
    } else {
        let ids = ids_of(r);
        let text = std::fs::read_to_string(deploy().join("tmpfiles.d/cncgw.conf")).unwrap();
        let numeric: String = text
            .lines()
            .map(|l| {
                let f: Vec<&str> = l.split_whitespace().collect();
                if l.trim_start().starts_with('#') || f.len() < 5 {
                    return l.to_string();
                }
                let id = |n: &str| ids.get(n).cloned().unwrap_or_else(|| n.to_string());
                format!("{} {} {} {} {} {}", f[0], f[1], f[2], id(f[3]), id(f[4]), f[5..].join(" "))
            })
            .collect::<Vec<_>>()
            .join("\n");
        let conf = r.join("cncgw-tmpfiles.conf");
        std::fs::write(&conf, numeric).unwrap();
        let o = Command::new("systemd-tmpfiles").arg(format!("--root={}", r.display())).arg("--create").arg(&conf).output().unwrap();
        assert!(o.status.success(), "systemd-tmpfiles: {}", String::from_utf8_lossy(&o.stderr));
        use std::os::unix::fs::MetadataExt;
        let uid: u32 = ids["cncgw"].parse().unwrap();
        for (p, mode) in [("var/lib/cncgw", 0o750), ("var/lib/cncgw/programs", 0o2770), ("var/lib/cncgw/state", 0o750)] {
            let m = std::fs::metadata(r.join(p)).unwrap();
            assert_eq!((m.uid(), m.mode() & 0o7777), (uid, mode), "{p}");
        }
    }

    // The units, installed with what they start, parse without a single warning.
    let unit_dir = r.join("etc/systemd/system");
    std::fs::create_dir_all(&unit_dir).unwrap();
    for (name, _) in units() {
        std::fs::copy(deploy().join("systemd").join(&name), unit_dir.join(&name)).unwrap();
    }
    let host_units = ["/usr/lib/systemd/system", "/lib/systemd/system"].into_iter().map(Path::new).find(|p| p.join("sysinit.target").exists());
    let Some(host_units) = host_units else {
        assert!(
            std::env::var("CI").as_deref() != Ok("true"),
            "no systemd unit directory with sysinit.target: install systemd (scripts/install-test-deps.sh)"
        );
        println!("SKIPPED: systemd-analyze verify: no systemd unit directory with sysinit.target on this host");
        return;
    };
    let lib = r.join("usr/lib/systemd/system");
    std::fs::create_dir_all(&lib).unwrap();
    for e in std::fs::read_dir(host_units).unwrap() {
        let p = e.unwrap().path();
        if p.is_file() {
            std::fs::copy(&p, lib.join(p.file_name().unwrap())).unwrap();
        }
    }
    for dir in ["usr/local/bin", "usr/local/lib/cncgw", "usr/sbin"] {
        std::fs::create_dir_all(r.join(dir)).unwrap();
    }
    std::fs::copy(env!("CARGO_BIN_EXE_cncgw"), r.join("usr/local/bin/cncgw")).unwrap();
    std::fs::copy(deploy().join("can-up.sh"), r.join("usr/local/lib/cncgw/can-up.sh")).unwrap();
    // `ip` (ExecStop of cncgw-can@): verify only needs an executable there.
    let ip = r.join("usr/sbin/ip");
    std::fs::write(&ip, "#!/bin/sh\n").unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&ip, std::fs::Permissions::from_mode(0o755)).unwrap();
    let o = Command::new("systemd-analyze")
        .args(["verify", "--man=no", "--generators=no"])
        .arg(format!("--root={}", r.display()))
        .args(["cncgw-run@o1000.service", "cncgw-can@can0.service"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success() && err.trim().is_empty(), "systemd-analyze verify: {err}");
}
