//! State kept through power-off — common variables #401–#600 (manual 004 §2.24.1), and any
//! other table the controller writes — stored so that a crash at any instant leaves the old
//! or the new file, never a torn one: write a temporary file in the same directory, fsync
//! it, rename it over the old one, fsync the directory.

use crate::Alarm;
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Alarm for a state file that cannot be read or written.
pub const STATE_ALARM: u32 = crate::alarm::STATE_FILE;

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
    let s: String = name.chars().map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '-' }).collect();
    let s = s.split('-').filter(|p| !p.is_empty()).collect::<Vec<_>>().join("-");
    if s.is_empty() {
        "machine".into()
    } else {
        s
    }
}

/// Where a machine's state files are and what they are called: one set per machine *and*
/// per place it runs — `inproc` for the embedded emulated machine (simulated time), else the
/// bus (`can0`, a socketcand URL, a Modbus link). So a simulated run never reads or writes a
/// real machine's common variables or tap state, and two machines of the same name on two
/// buses keep theirs apart.
pub struct StatePlace {
    pub dir: PathBuf,
    /// The files' stem: `MACHINE@PLACE`.
    pub key: String,
    /// What changed on the way (a state file of an earlier version taken over), to tell.
    pub notes: Vec<String>,
}

impl StatePlace {
    /// The state of machine `name` running on `place` in `dir`. A state file of the earlier
    /// naming (`MACHINE.*.toml`, one per machine) is taken over for a real bus, and said so;
    /// the embedded machine never takes it (it may be a real machine's).
    pub fn new(dir: &Path, name: &str, place: &str) -> StatePlace {
        let key = format!("{}@{}", slug(name), place_slug(place));
        let mut notes = Vec::new();
        for kind in ["common-vars", "tap-state"] {
            let old = dir.join(format!("{}.{kind}.toml", slug(name)));
            let new = dir.join(format!("{key}.{kind}.toml"));
            if old.exists() && !new.exists() {
                if place == "inproc" {
                    notes.push(format!(
                        "{} is left alone: it may be a real machine's; the embedded machine keeps its own in {}",
                        old.display(),
                        new.display()
                    ));
                } else if std::fs::rename(&old, &new).is_ok() {
                    notes.push(format!("{} renamed to {} (state is kept per machine and bus now)", old.display(), new.display()));
                }
            }
        }
        StatePlace { dir: dir.to_path_buf(), key, notes }
    }

    pub fn common_vars(&self) -> CommonVarsFile {
        CommonVarsFile { path: self.dir.join(format!("{}.common-vars.toml", self.key)) }
    }

    pub fn tap_state(&self) -> TapStateFile {
        TapStateFile { path: self.dir.join(format!("{}.tap-state.toml", self.key)) }
    }

    /// The axes' reference (home) state (`reference`).
    pub fn reference(&self) -> crate::reference::ReferenceFile {
        crate::reference::ReferenceFile { path: self.dir.join(format!("{}.reference.toml", self.key)) }
    }

    pub fn alarm_history(&self) -> AlarmHistory {
        AlarmHistory { path: self.dir.join(format!("{}.alarms.jsonl", self.key)) }
    }

    /// Everything that can be checked before motion: the directory exists (or can be made)
    /// and a file can be written into it.
    pub fn check_writable(&self) -> Result<(), Alarm> {
        let probe = self.dir.join(format!(".{}.probe-{}", self.key, std::process::id()));
        std::fs::create_dir_all(&self.dir).and_then(|_| std::fs::write(&probe, b"probe")).and_then(|_| std::fs::remove_file(&probe)).map_err(|e| {
            Alarm::new(
                STATE_ALARM,
                format!(
                    "the state directory {} cannot be written ({e}): give a writable one with --state-dir or $CNCGW_STATE_DIR; nothing was moved",
                    self.dir.display()
                ),
            )
        })
    }
}

/// A place (bus or `inproc`) as part of a file name.
fn place_slug(place: &str) -> String {
    let s: String = place.chars().map(|c| if c.is_ascii_alphanumeric() || c == '.' || c == '-' { c } else { '_' }).collect();
    if s.is_empty() {
        "none".into()
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
        atomic_write(&self.path, format_common_vars(vars).as_bytes()).map_err(|e| {
            Alarm::new(
                STATE_ALARM,
                format!("{}: cannot store the common variables: {e}; check the state directory (--state-dir)", self.path.display()),
            )
        })
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

/// The rigid-tap state (manual 000, "刚性攻丝返回"): what `G30 P99` needs to bring a tap out of
/// a hole after an interruption — reset, E-stop, feed hold abort or the controller dying. It is
/// on disk while the tool is in the hole (written at the entry and every few ms while the tap
/// runs, see `control::tapstate`), and says "not in a hole" once the tool is back at R.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TapState {
    /// The tool is inside a tapped hole: a program other than `G30 P99` must not start.
    pub in_hole: bool,
    /// Tapping axis: `'X'`, `'Y'` or `'Z'`.
    pub axis: char,
    /// The R plane on that axis (machine mm, X as a radius).
    pub r_plane: f64,
    /// Direction into the hole along the axis (+1 or −1).
    pub direction_in: f64,
    /// Lead, signed as in `canon::MoveKind::Tap` (the spindle turns forward going in).
    pub lead: f64,
    /// Tapping spindle speed going in (rpm).
    pub rpm: f64,
    /// Pull-out override of the hole (%; 100 when the hole's return was not planned yet).
    pub override_pct: f64,
    /// Actual position on the tapping axis (mm) and actual spindle angle (degrees, as the
    /// master unwraps it) at one instant: a point of the thread. With `lead` it is the
    /// thread's phase, against which a restart can check where the spindle stands.
    pub position: f64,
    pub spindle_deg: f64,
    /// Source line of the tap.
    pub line: u32,
}

impl TapState {
    /// What the interpreter's `G30 P99` returns along.
    pub fn tap_return(&self) -> crate::canon::TapReturn {
        // Spindle 1: the only one motion taps with (it refuses a tap on another, alarm 2304).
        crate::canon::TapReturn {
            axis: self.axis,
            r_plane: self.r_plane,
            lead: self.lead,
            rpm: self.rpm,
            override_pct: self.override_pct,
            spindle: 1,
        }
    }

    /// How far (degrees) the spindle at `spindle_deg` stands from the stored thread when the
    /// tapping axis is at `position`: 0 when nothing turned the spindle against the axis.
    pub fn phase_error_deg(&self, position: f64, spindle_deg: f64) -> f64 {
        spindle_deg - (self.spindle_deg + 360.0 * (position - self.position) / self.lead)
    }
}

/// The rigid-tap state file of one machine (beside its common variables).
pub struct TapStateFile {
    pub path: PathBuf,
}

impl TapStateFile {
    pub fn new(dir: &Path, machine_name: &str) -> Self {
        TapStateFile { path: dir.join(format!("{}.tap-state.toml", slug(machine_name))) }
    }

    /// The stored state; None if there is no file (no tap was ever interrupted or finished).
    pub fn load(&self) -> Result<Option<TapState>, Alarm> {
        self.remove_stale_temporaries();
        let text = match std::fs::read_to_string(&self.path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Alarm::new(STATE_ALARM, format!("{}: cannot read the rigid-tap state: {e}", self.path.display()))),
        };
        parse_tap_state(&self.path.display().to_string(), &text).map(Some)
    }

    /// Temporary files of writers killed mid-write (`atomic_write` names them
    /// `.NAME.PID.SEQ.tmp`); those of live processes are left alone.
    fn remove_stale_temporaries(&self) {
        let (Some(dir), Some(name)) = (self.path.parent(), self.path.file_name()) else { return };
        let prefix = format!(".{}.", name.to_string_lossy());
        let Ok(entries) = std::fs::read_dir(if dir.as_os_str().is_empty() { Path::new(".") } else { dir }) else { return };
        for e in entries.flatten() {
            let n = e.file_name().to_string_lossy().into_owned();
            let pid =
                n.strip_prefix(&prefix).and_then(|r| r.strip_suffix(".tmp")).and_then(|r| r.split('.').next()).and_then(|p| p.parse::<u32>().ok());
            if let Some(pid) = pid {
                if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
                    let _ = std::fs::remove_file(e.path());
                }
            }
        }
    }

    pub fn save(&self, st: &TapState) -> Result<(), Alarm> {
        atomic_write(&self.path, format_tap_state(st).as_bytes()).map_err(|e| {
            Alarm::new(
                STATE_ALARM,
                format!("{}: cannot store the rigid-tap state: {e}; check the state directory (--state-dir)", self.path.display()),
            )
        })
    }
}

/// FNV-1a 64 of `b`: the tap-state file's own check, so that a file that is not one whole
/// generation (which atomic replacement should make impossible) is refused, not half-read.
fn fnv1a64(b: &[u8]) -> u64 {
    b.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, x| (h ^ *x as u64).wrapping_mul(0x0100_0000_01b3))
}

/// TOML, the floats with every bit (`{:?}`), and a last line `check = "…"` over the rest.
pub fn format_tap_state(st: &TapState) -> String {
    let body = format!(
        "# cncgw rigid-tap state (G30 P99 returns along it); written atomically while a tap runs\n\
         in_hole = {}\naxis = \"{}\"\nr_plane = {:?}\ndirection_in = {:?}\nlead = {:?}\nrpm = {:?}\noverride_pct = {:?}\n\
         position = {:?}\nspindle_deg = {:?}\nline = {}\n",
        st.in_hole, st.axis, st.r_plane, st.direction_in, st.lead, st.rpm, st.override_pct, st.position, st.spindle_deg, st.line
    );
    let h = fnv1a64(body.as_bytes());
    format!("{body}check = \"{h:016x}\"\n")
}

pub fn parse_tap_state(file: &str, text: &str) -> Result<TapState, Alarm> {
    let bad = |what: &str| {
        Alarm::new(
            STATE_ALARM,
            format!("{file}: the rigid-tap state is {what}; if a tap was interrupted, bring the tool out of the hole by hand, then delete the file"),
        )
    };
    let body_end = text.rfind("check = \"").ok_or_else(|| bad("incomplete (no check line)"))?;
    let (body, check) = text.split_at(body_end);
    let want = check.trim_end().strip_prefix("check = \"").and_then(|c| c.strip_suffix('"')).and_then(|c| u64::from_str_radix(c, 16).ok());
    if want != Some(fnv1a64(body.as_bytes())) {
        return Err(bad("damaged (check mismatch)"));
    }
    let st: TapState = toml::from_str(body).map_err(|e| bad(&format!("unreadable ({e})")))?;
    let finite = [st.r_plane, st.lead, st.rpm, st.override_pct, st.position, st.spindle_deg].iter().all(|v| v.is_finite());
    if !finite
        || !matches!(st.axis, 'X' | 'Y' | 'Z')
        || st.lead == 0.0
        || st.direction_in.abs() != 1.0
        || st.rpm.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
    {
        return Err(bad("out of range"));
    }
    Ok(st)
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

    fn tap() -> TapState {
        TapState {
            in_hole: true,
            axis: 'Z',
            r_plane: 2.0,
            direction_in: -1.0,
            lead: -1.5,
            rpm: 500.0,
            override_pct: 120.0,
            position: -7.123456789,
            spindle_deg: 2214.5 + 1.0 / 3.0,
            line: 4,
        }
    }

    #[test]
    fn tap_state_round_trip_and_check() {
        let text = format_tap_state(&tap());
        assert_eq!(parse_tap_state("t", &text).unwrap(), tap());
        // Any truncation (a torn file) or changed byte is refused.
        for cut in [10, text.len() / 2, text.len() - 3] {
            assert!(parse_tap_state("t", &text[..cut]).is_err(), "cut at {cut}");
        }
        let changed = text.replace("position = -7.1", "position = -7.2");
        assert!(parse_tap_state("t", &changed).unwrap_err().message.contains("damaged"));
        let t = tap();
        assert!((t.phase_error_deg(t.position - 1.5, t.spindle_deg + 360.0)).abs() < 1e-9, "one lead further in is one turn forward");
        assert!((t.phase_error_deg(t.position, t.spindle_deg + 10.0) - 10.0).abs() < 1e-9);
    }

    #[test]
    fn tap_state_file_save_load() {
        let dir = std::env::temp_dir().join(format!("cncgw-tapstate-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let f = TapStateFile::new(&dir, "Test lathe #1");
        assert_eq!(f.path.file_name().unwrap(), "test-lathe-1.tap-state.toml");
        assert_eq!(f.load().unwrap(), None);
        f.save(&tap()).unwrap();
        assert_eq!(f.load().unwrap(), Some(tap()));
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// The alarms a machine has had, one JSON object per line (`{"time", "number", "message",
/// "file", "line", "program"}`), appended as they happen so that the operator can read them
/// later (`cncgw alarms`), as a Fanuc's alarm history page.
#[derive(Clone, Debug)]
pub struct AlarmHistory {
    pub path: PathBuf,
}

/// One entry of the alarm history.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AlarmRecord {
    /// RFC 3339, UTC, seconds.
    pub time: String,
    pub number: u32,
    pub message: String,
    pub file: Option<String>,
    pub line: Option<u32>,
    /// The program that ran.
    pub program: String,
}

impl AlarmHistory {
    /// Append `a` (raised while `program` ran) with the present time. One `write` of one line
    /// on a file opened for appending: entries of two processes never interleave.
    pub fn append(&self, a: &Alarm, program: &str) -> std::io::Result<()> {
        use std::io::Write;
        let rec = AlarmRecord {
            time: humantime::format_rfc3339_seconds(std::time::SystemTime::now()).to_string(),
            number: a.number,
            message: a.message.clone(),
            file: a.pos.as_ref().map(|p| p.file.to_string()),
            line: a.pos.as_ref().map(|p| p.line),
            program: program.to_string(),
        };
        let mut line = serde_json::to_string(&rec).map_err(std::io::Error::other)?;
        line.push('\n');
        if let Some(d) = self.path.parent() {
            std::fs::create_dir_all(d)?;
        }
        std::fs::OpenOptions::new().create(true).append(true).open(&self.path)?.write_all(line.as_bytes())
    }

    /// Every entry at or after `since` (all with None), oldest first; lines that cannot be
    /// read (a torn last line after a power cut) are skipped.
    pub fn read(&self, since: Option<std::time::SystemTime>) -> std::io::Result<Vec<AlarmRecord>> {
        let text = match std::fs::read_to_string(&self.path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(e),
        };
        Ok(text
            .lines()
            .filter_map(|l| serde_json::from_str::<AlarmRecord>(l).ok())
            .filter(|r| since.is_none_or(|s| humantime::parse_rfc3339(&r.time).is_ok_and(|t| t >= s)))
            .collect())
    }
}
