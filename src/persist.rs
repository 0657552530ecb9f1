//! State kept through power-off — common variables #401–#600 (manual 004 §2.24.1), and any
//! other table the controller writes — stored so that a crash at any instant leaves the old
//! or the new file, never a torn one: write a temporary file in the same directory, fsync
//! it, rename it over the old one, fsync the directory.

use crate::Alarm;
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Alarm for a state file that cannot be read or written.
pub const STATE_ALARM: u32 = 1100;

/// Replace `path` with `data` atomically (see the module doc).
pub fn atomic_write(path: &Path, data: &[u8]) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir)?;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "state".into());
    // Unique per process and call: two writers never share a temporary file.
    static SEQ: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let seq = SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.{}.{seq}.tmp", std::process::id()));
    let r = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(data)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        // The rename itself must reach the disk.
        std::fs::File::open(&dir)?.sync_all()
    })();
    if r.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    r
}

/// Where a machine's state lives: `--state-dir`, else `$CNCGW_STATE_DIR`, else
/// `$XDG_STATE_HOME/cncgw`, else `~/.local/state/cncgw`.
pub fn default_state_dir() -> Option<PathBuf> {
    if let Some(d) = std::env::var_os("CNCGW_STATE_DIR") {
        return Some(PathBuf::from(d));
    }
    if let Some(d) = std::env::var_os("XDG_STATE_HOME") {
        return Some(PathBuf::from(d).join("cncgw"));
    }
    std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/state/cncgw"))
}

/// A file name from a machine's name: letters, digits and `-`.
pub fn slug(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '-' })
        .collect();
    let s = s.split('-').filter(|p| !p.is_empty()).collect::<Vec<_>>().join("-");
    if s.is_empty() {
        "machine".into()
    } else {
        s
    }
}

/// The common-variable file of one machine.
pub struct CommonVarsFile {
    pub path: PathBuf,
}

impl CommonVarsFile {
    pub fn new(dir: &Path, machine_name: &str) -> Self {
        CommonVarsFile { path: dir.join(format!("{}.common-vars.toml", slug(machine_name))) }
    }

    /// The stored variables; none if the file does not exist yet.
    pub fn load(&self) -> Result<HashMap<u32, f64>, Alarm> {
        let text = match std::fs::read_to_string(&self.path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(HashMap::new()),
            Err(e) => return Err(Alarm::new(STATE_ALARM, format!("{}: cannot read the common variables: {e}", self.path.display()))),
        };
        parse_common_vars(&self.path.display().to_string(), &text)
    }

    pub fn save(&self, vars: &HashMap<u32, f64>) -> Result<(), Alarm> {
        atomic_write(&self.path, format_common_vars(vars).as_bytes())
            .map_err(|e| Alarm::new(STATE_ALARM, format!("{}: cannot store the common variables: {e}; check the state directory (--state-dir)", self.path.display())))
    }
}

/// `"#401" = 1.5` lines, sorted, with a header.
pub fn format_common_vars(vars: &HashMap<u32, f64>) -> String {
    let sorted: BTreeMap<u32, f64> = vars.iter().filter(|(_, v)| v.is_finite()).map(|(k, v)| (*k, *v)).collect();
    let mut s = String::from("# cncgw common variables #401-#600, kept through power-off (written atomically)\n");
    for (k, v) in sorted {
        // `{:?}` keeps every bit of an f64 and always has a decimal point (valid TOML float).
        s.push_str(&format!("\"#{k}\" = {v:?}\n"));
    }
    s
}

pub fn parse_common_vars(file: &str, text: &str) -> Result<HashMap<u32, f64>, Alarm> {
    let t: BTreeMap<String, toml::Value> =
        toml::from_str(text).map_err(|e| Alarm::new(STATE_ALARM, format!("{file}: common variables unreadable: {e}")))?;
    let mut out = HashMap::new();
    for (k, v) in t {
        let n = k.strip_prefix('#').and_then(|n| n.parse::<u32>().ok()).filter(|n| crate::interp::macros::is_common(*n));
        let val = v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
        match (n, val) {
            (Some(n), Some(x)) if x.is_finite() => {
                out.insert(n, x);
            }
            _ => return Err(Alarm::new(STATE_ALARM, format!("{file}: {k:?} = {v}: expected \"#401\"…\"#600\" = number"))),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_every_bit() {
        let vars: HashMap<u32, f64> = [(401, 1.0 / 3.0), (600, -0.0), (500, 1e300), (450, 42.0)].into_iter().collect();
        let text = format_common_vars(&vars);
        let back = parse_common_vars("t", &text).unwrap();
        for (k, v) in &vars {
            assert_eq!(back[k].to_bits(), v.to_bits(), "#{k}");
        }
    }

    #[test]
    fn bad_entries_are_alarms() {
        assert!(parse_common_vars("t", "\"#1\" = 3.0\n").is_err(), "a local is not a common variable");
        assert!(parse_common_vars("t", "\"#401\" = \"x\"\n").is_err());
        assert!(parse_common_vars("t", "\"#401\" = 1.0\n\"#40").is_err(), "a torn file is refused, not half-read");
    }

    #[test]
    fn atomic_write_replaces_and_leaves_no_temporary() {
        let dir = std::env::temp_dir().join(format!("cncgw-persist-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let f = CommonVarsFile::new(&dir, "Test lathe #1");
        assert_eq!(f.path.file_name().unwrap(), "test-lathe-1.common-vars.toml");
        assert!(f.load().unwrap().is_empty());
        f.save(&[(401, 1.5)].into_iter().collect()).unwrap();
        f.save(&[(401, 2.5), (402, 7.0)].into_iter().collect()).unwrap();
        let v = f.load().unwrap();
        assert_eq!((v[&401], v[&402]), (2.5, 7.0));
        let names: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names.len(), 1, "{names:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
