//! The Type A G-code table (manual table 1.1) with modal groups, and block decoding:
//! evaluated words → one [`Decoded`] block, with the checks that need no modal state.
//!
//! The manual's table 1.1 lists the codes but not their groups; the groups are Fanuc
//! 0i-TF's (00 one-shot, 01 motion, 02 G96/G97, 04 G22/G23, 05 G98/G99, 06 G20/G21,
//! 07 G40–G42, 10 G80–G89, 14 G54–G59, 15 G61/G64, 16 G17–G19, 20 G50.2/G51.2,
//! 21 G12.1/G13.1). Two codes of one group in a block → alarm 10 (the manual's §2.14 item 3
//! ties G61/G64 to a group; Fanuc would take the last one, we refuse the ambiguity).

/// A G code ×10 (`G02.1` → 21, `G54` → 540), so that the decimal codes fit an integer.
pub type GCode = u16;

pub struct GInfo {
    pub group: u8,
    pub name: &'static str,
    /// None = implemented; Some(why) = recognised but not implemented yet.
    pub unsupported: Option<&'static str>,
}

// (`unsupported: Some("not supported yet")` marks a code recognised but not implemented;
// every code of table 1.1 is implemented now.)

pub fn ginfo(g: GCode) -> Option<GInfo> {
    let (group, name, unsupported) = match g {
        0 => (1, "rapid positioning", None),
        10 => (1, "linear interpolation", None),
        20 => (1, "circular interpolation CW", None),
        30 => (1, "circular interpolation CCW", None),
        21 => (1, "elliptical interpolation CW", None),
        31 => (1, "elliptical interpolation CCW", None),
        22 => (1, "parabolic interpolation CW", None),
        32 => (1, "parabolic interpolation CCW", None),
        40 => (0, "dwell", None),
        90 => (0, "exact stop check", None),
        121 => (21, "polar coordinate interpolation", None),
        131 => (21, "polar coordinate interpolation cancel", None),
        170 => (16, "XY plane", None),
        180 => (16, "ZX plane", None),
        190 => (16, "YZ plane", None),
        200 => (6, "inch input", None),
        210 => (6, "metric input", None),
        220 => (4, "stored stroke check 2 on", None),
        230 => (4, "stored stroke check 2 off", None),
        280 => (0, "reference point return", None),
        300 => (0, "2nd/3rd/4th reference point return", None),
        320 => (1, "thread cutting", None),
        340 => (1, "variable-lead thread cutting", None),
        400 => (7, "tool nose radius compensation cancel", None),
        410 => (7, "tool nose radius compensation left", None),
        420 => (7, "tool nose radius compensation right", None),
        500 => (0, "coordinate system setting / max spindle speed", None),
        502 => (20, "polygon turning cancel", None),
        512 => (20, "polygon turning", None),
        520 => (0, "local coordinate system", None),
        530 => (0, "machine coordinate positioning", None),
        540 | 550 | 560 | 570 | 580 | 590 => (14, "workpiece coordinate system", None),
        610 => (15, "exact stop mode", None),
        640 => (15, "continuous path mode", None),
        650 => (0, "macro call", None),
        700 => (0, "finishing cycle", None),
        710 => (0, "stock removal in turning", None),
        720 => (0, "stock removal in facing", None),
        730 => (0, "pattern repeating", None),
        740 => (0, "face grooving cycle", None),
        750 => (0, "OD/ID grooving cycle", None),
        760 => (0, "multiple thread cutting cycle", None),
        780 => (0, "enhanced multiple thread cutting cycle (manual 002)", None),
        800 => (10, "canned drilling cycle cancel", None),
        830 => (10, "face drilling cycle", None),
        840 => (10, "face tapping cycle", None),
        850 => (10, "face boring cycle", None),
        870 => (10, "side drilling cycle", None),
        880 => (10, "side tapping cycle", None),
        890 => (10, "side boring cycle", None),
        900 => (1, "OD/ID turning cycle", None),
        920 => (1, "thread cutting cycle", None),
        921 => (1, "rigid thread cutting cycle (manual 001)", None),
        940 => (1, "facing cycle", None),
        960 => (2, "constant surface speed", None),
        970 => (2, "constant spindle speed", None),
        980 => (5, "feed per minute", None),
        990 => (5, "feed per revolution", None),
        _ => return None,
    };
    Some(GInfo { group, name, unsupported })
}

pub fn gname(g: GCode) -> String {
    if g % 10 == 0 {
        format!("G{:02}", g / 10)
    } else {
        format!("G{:02}.{}", g / 10, g % 10)
    }
}

// The codes the interpreter's block dispatcher (`Interp::exec_block`) tests by value.
pub const G_DWELL: GCode = 40;
pub const G_EXACT_STOP: GCode = 90;
pub const G_PLANE_XY: GCode = 170;
pub const G_PLANE_YZ: GCode = 190;
pub const G_INCH: GCode = 200;
pub const G_REF_RETURN: GCode = 280;
pub const G_REF_RETURN_2: GCode = 300;
pub const G_NRC_LEFT: GCode = 410;
pub const G_NRC_RIGHT: GCode = 420;
pub const G_SET_COORD: GCode = 500;
pub const G_LOCAL_COORD: GCode = 520;
pub const G_MACHINE_COORD: GCode = 530;
/// G54; G55–G59 follow in steps of 10.
pub const G_WCS_FIRST: GCode = 540;
pub const G_EXACT_MODE: GCode = 610;
pub const G_MACRO_CALL: GCode = 650;
pub const G_FINISHING: GCode = 700;
pub const G_STOCK_TURNING: GCode = 710;
pub const G_STOCK_FACING: GCode = 720;
pub const G_PATTERN_REPEAT: GCode = 730;
pub const G_FACE_GROOVING: GCode = 740;
pub const G_OD_GROOVING: GCode = 750;
pub const G_THREAD_MULTI: GCode = 760;
pub const G_THREAD_MULTI_ENH: GCode = 780;
pub const G_RIGID_THREAD: GCode = 921;
pub const G_CSS: GCode = 960;
pub const G_CONST_RPM: GCode = 970;
pub const G_PER_REV: GCode = 990;

/// `x.round()` (half away from zero) without the libm call that `f64::round` compiles to
/// on a baseline x86-64 target; the interpreter and `plan` round several times per block.
#[inline]
pub fn round(x: f64) -> f64 {
    if x.abs() < 4.0e15 {
        let t = x as i64 as f64; // truncation: exact below 2^52
        let f = x - t;
        let r = if f >= 0.5 {
            t + 1.0
        } else if f <= -0.5 {
            t - 1.0
        } else {
            t
        };
        r.copysign(x) // -0.3 rounds to -0.0, as f64::round does
    } else {
        x.round()
    }
}

/// One evaluated word.
#[derive(Clone, Copy, Debug, Default)]
pub struct Val {
    pub v: f64,
    /// Written with a decimal point (values from variables count as having one).
    pub decimal: bool,
    pub col: u32,
    /// Written as a literal (not from a variable or expression).
    pub literal: bool,
}

impl Val {
    /// Breaks the rule "no decimal point" for integer addresses: a literal written with a
    /// point, or a computed value with a fraction.
    pub fn bad_integer(&self) -> bool {
        if self.literal {
            self.decimal
        } else {
            self.v.fract() != 0.0
        }
    }
}

/// A short list kept inline (a block's G or M codes): decoding a block allocates nothing.
/// Reads like a slice (`iter`, `len`, `first`, indexing).
#[derive(Clone, Copy, Debug)]
pub struct Inline<T: Copy + Default, const N: usize> {
    items: [T; N],
    len: usize,
}

impl<T: Copy + Default, const N: usize> Default for Inline<T, N> {
    fn default() -> Self {
        Inline { items: [T::default(); N], len: 0 }
    }
}

impl<T: Copy + Default, const N: usize> Inline<T, N> {
    pub fn clear(&mut self) {
        self.len = 0;
    }
    /// False when full.
    pub fn push(&mut self, v: T) -> bool {
        if self.len == N {
            return false;
        }
        self.items[self.len] = v;
        self.len += 1;
        true
    }
}

impl<T: Copy + Default, const N: usize> std::ops::Deref for Inline<T, N> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        &self.items[..self.len]
    }
}

impl<'a, T: Copy + Default, const N: usize> IntoIterator for &'a Inline<T, N> {
    type Item = &'a T;
    type IntoIter = std::slice::Iter<'a, T>;
    fn into_iter(self) -> Self::IntoIter {
        self.items[..self.len].iter()
    }
}

/// At most this many G codes in one block (one per modal group is the real limit).
pub const MAX_G_PER_BLOCK: usize = 16;

/// A decoded NC block.
#[derive(Clone, Debug, Default)]
pub struct Decoded {
    pub g: Inline<(GCode, u32), MAX_G_PER_BLOCK>,
    /// At most three M codes per block (checked in [`Decoded::build`]).
    pub m: Inline<(u32, u32), 3>,
    /// Modal group of each code of `g` (looked up once: blocks ask for groups often).
    groups: Inline<u8, MAX_G_PER_BLOCK>,
    /// Bit i set: address `'A' + i` is in the block (its value in `addr[i]`).
    mask: u32,
    addr: [Val; 26],
    pub comma_c: Option<Val>,
    pub comma_r: Option<Val>,
}

/// A decoding error: alarm number, column, message.
pub type DErr = (u32, u32, String);

impl Decoded {
    #[inline]
    pub fn get(&self, l: char) -> Option<Val> {
        let i = (l as u32).wrapping_sub('A' as u32);
        if i < 26 && self.mask >> i & 1 == 1 {
            Some(self.addr[i as usize])
        } else {
            None
        }
    }
    #[inline]
    pub fn has(&self, l: char) -> bool {
        let i = (l as u32).wrapping_sub('A' as u32);
        i < 26 && self.mask >> i & 1 == 1
    }
    pub fn has_g(&self, g: GCode) -> bool {
        self.g.iter().any(|x| x.0 == g)
    }
    /// The code of `group` in this block, if any.
    pub fn group(&self, group: u8) -> Option<GCode> {
        self.groups.iter().position(|&x| x == group).map(|i| self.g[i].0)
    }
    pub fn letters(&self) -> impl Iterator<Item = char> + '_ {
        (0..26u8).filter(move |i| self.mask >> i & 1 == 1).map(|i| (b'A' + i) as char)
    }

    /// Build from evaluated words `(letter, comma, value)`; checks that need no modal state.
    /// `has_y` / `has_c`: whether the machine has a Y axis / a C (Cs) axis.
    pub fn build(words: &[(char, bool, Val)], has_y: bool, has_c: bool) -> Result<Decoded, DErr> {
        let mut d = Decoded::default();
        d.fill(words, has_y, has_c)?;
        Ok(d)
    }

    /// Whether [`Decoded::fill`] of `words` is bound to succeed because it succeeded for
    /// `prev`, with `self` then holding everything the static check reads afterwards (the
    /// M codes, G codes and P): the checks of `fill` look only at the letters (in order), the
    /// values and decimal points of G, M, T, L, D and P, and the machine's axes (the same
    /// for both). A block with P is never taken: P's column is read afterwards (the first
    /// pass of a CAM program checks most blocks this way, at a fraction of the cost).
    pub fn same_checks(words: &[(char, bool, Val)], prev: &[(char, bool, Val)]) -> bool {
        words.len() == prev.len()
            && words.iter().zip(prev).all(|(a, b)| {
                a.0 == b.0
                    && a.0 != 'P'
                    && !a.1
                    && !b.1
                    && a.2.literal
                    && b.2.literal
                    && (!matches!(a.0, 'G' | 'M' | 'T' | 'L' | 'D') || (a.2.v.to_bits() == b.2.v.to_bits() && a.2.decimal == b.2.decimal))
            })
    }

    /// [`Decoded::fill`] of `words` when [`Decoded::same_checks`] says they are shaped like
    /// the words `self` was last filled from: the codes, groups and letters stay, only the
    /// values and columns change, so the result is the one `fill` would give.
    fn refill(&mut self, words: &[(char, bool, Val)]) {
        let (mut gi, mut mi) = (0, 0);
        for &(l, _, val) in words {
            match l {
                'G' => {
                    if let Some(e) = self.g.items.get_mut(gi) {
                        e.1 = val.col;
                    }
                    gi += 1;
                }
                'M' => {
                    if let Some(e) = self.m.items.get_mut(mi) {
                        e.1 = val.col;
                    }
                    mi += 1;
                }
                _ => {
                    if let Some(a) = self.addr.get_mut((l as usize).wrapping_sub('A' as usize)) {
                        *a = val;
                    }
                }
            }
        }
    }

    /// [`Decoded::build`] into `self` (emptied first), so that a decoder kept across blocks
    /// is neither initialised nor copied per block.
    pub fn fill(&mut self, words: &[(char, bool, Val)], has_y: bool, has_c: bool) -> Result<(), DErr> {
        let d = self;
        d.g.clear();
        d.m.clear();
        d.groups.clear();
        d.mask = 0;
        d.comma_c = None;
        d.comma_r = None;
        let mut any_unsupported = false;
        // G78 (manual 002) uses J as its run-out amount, not as the Y axis.
        let (mut g78, mut tap) = (false, false);
        for w in words.iter().filter(|w| w.0 == 'G') {
            let code = round(w.2.v * 10.0);
            g78 |= code == 780.0;
            tap |= code == 840.0 || code == 880.0;
        }
        // G84/G88 (manual 000): J is the pull-out spindle speed, D the peck return (mm).
        for &(l, comma, val) in words {
            if comma {
                let slot = if l == 'C' { &mut d.comma_c } else { &mut d.comma_r };
                // Manual §2.23 note 9: of several ,C / ,R the last is effective.
                *slot = Some(val);
                continue;
            }
            match l {
                'G' => {
                    let code = round(val.v * 10.0);
                    let g = code as GCode;
                    let info = if (code - val.v * 10.0).abs() > 1e-6 || !(0.0..=9999.0).contains(&code) { None } else { ginfo(g) };
                    let Some(info) = info else {
                        let shown = if val.v.fract() == 0.0 && val.v >= 0.0 { format!("G{:02}", val.v) } else { format!("G{}", val.v) };
                        return Err((10, val.col, format!("{shown}: not a G code of this control (Type A lathe, table 1.1)")));
                    };
                    any_unsupported |= info.unsupported.is_some();
                    if !d.g.push((g, val.col)) {
                        return Err((10, val.col, format!("more than {MAX_G_PER_BLOCK} G codes in one block")));
                    }
                    d.groups.push(info.group);
                }
                'M' => {
                    if val.v < 0.0 {
                        return Err((6, val.col, "an M code cannot be negative".into()));
                    }
                    if val.v > 99_999_999.0 {
                        return Err((3, val.col, "M code with too many digits".into()));
                    }
                    if val.bad_integer() {
                        return Err((7, val.col, "an M code takes no decimal point".into()));
                    }
                    if d.m.len() >= 3 {
                        return Err((9, val.col, "at most three M codes per block".into()));
                    }
                    d.m.push((round(val.v) as u32, val.col));
                    // (capacity 3 = the limit checked just above)
                }
                _ => {
                    if matches!(l, 'Y' | 'V' | 'J') && !has_y && !(l == 'J' && (g78 || tap)) {
                        return Err((9, val.col, format!("address {l}: this machine has no Y axis")));
                    }
                    if matches!(l, 'C' | 'H') && !has_c {
                        return Err((9, val.col, format!("address {l}: this machine has no C (Cs) axis")));
                    }
                    if matches!(l, 'T' | 'L' | 'D' | 'P') && val.v < 0.0 && !val.literal {
                        return Err((6, val.col, format!("address {l} cannot be negative")));
                    }
                    if matches!(l, 'T' | 'L' | 'D') && val.bad_integer() && !(l == 'D' && tap) {
                        return Err((7, val.col, format!("address {l} takes no decimal point")));
                    }
                    let i = (l as u8).wrapping_sub(b'A') as usize;
                    if i >= 26 {
                        return Err((9, val.col, format!("improper address `{l}`")));
                    }
                    if d.mask >> i & 1 == 1 {
                        return Err((9, val.col, format!("address {l} appears twice in the block")));
                    }
                    d.mask |= 1 << i;
                    d.addr[i] = val;
                }
            }
        }
        // Modal groups: at most one code per group.
        for (i, &(g, col)) in d.g.iter().enumerate() {
            let gi = d.groups[i];
            for (j, &(h, _)) in d.g[..i].iter().enumerate() {
                if d.groups[j] == gi {
                    return Err((10, col, format!("{} and {} are of the same group ({:02}); command only one", gname(h), gname(g), gi)));
                }
            }
        }
        for &(g, col) in d.g.iter().filter(|_| any_unsupported) {
            if let Some(GInfo { unsupported: Some(why), name, .. }) = ginfo(g) {
                return Err((10, col, format!("{} ({name}) is {why}", gname(g))));
            }
        }
        // Manual §2.9 note 2 (G20/G21 alone, at the start) needs the modal unit: checked when
        // the block runs (Interpreter::unit_block), a code that switches nothing may share.
        // Manual §3.1.7 note 1: M99 alone in its block (P allowed). M98 runs after the
        // block's other codes (§3.1.6), but its P cannot be shared with a G code using P.
        for &(m, col) in &d.m {
            if m == 99 && (d.m.len() > 1 || !d.g.is_empty() || d.letters().any(|l| l != 'P')) {
                return Err((9, col, "M99 must be alone in its block (M99 or M99 Pn)".into()));
            }
            if m == 98 {
                if let Some(&(g, _)) = d.g.iter().find(|g| matches!(g.0, 40 | 300 | 650)) {
                    return Err((9, col, format!("M98 P cannot share its block with {} (which uses P too)", gname(g))));
                }
                if d.m.iter().any(|x| matches!(x.0, 2 | 30 | 99)) {
                    return Err((9, col, "M98 cannot share its block with M02/M30/M99".into()));
                }
            }
        }
        // P is an integer in G04 (ms, manual §2.6), M98/M99 and G65.
        if let Some(p) = d.get('P') {
            if p.bad_integer() && (d.has_g(40) || d.has_g(650) || d.m.iter().any(|m| m.0 == 98 || m.0 == 99)) {
                return Err((7, p.col, "P takes no decimal point here (G04 P is in ms: G04 P500)".into()));
            }
        }
        for (l, u) in [('X', 'U'), ('Z', 'W'), ('Y', 'V'), ('C', 'H')] {
            if let (Some(_), Some(b)) = (d.get(l), d.get(u)) {
                if !d.has_g(40) {
                    return Err((9, b.col, format!("{l} (absolute) and {u} (incremental) of one axis in one block")));
                }
            }
        }
        Ok(())
    }
}

/// A [`Decoded`] kept across blocks with the words it was last filled from successfully: a
/// block shaped like those ([`Decoded::same_checks`]; nearly every block of a CAM program
/// is shaped like the one before) is decoded by updating its values only.
pub struct BlockDecoder {
    pub d: Decoded,
    words: [(char, bool, Val); crate::interp::parse::FAST_WORDS],
    ok_len: Option<usize>,
}

impl Default for BlockDecoder {
    fn default() -> Self {
        BlockDecoder { d: Decoded::default(), words: [crate::interp::parse::NO_WORD; crate::interp::parse::FAST_WORDS], ok_len: None }
    }
}

impl BlockDecoder {
    /// [`Decoded::fill`] of `words` into `self.d`.
    pub fn decode(&mut self, words: &[(char, bool, Val)], has_y: bool, has_c: bool) -> Result<(), DErr> {
        if self.ok_len.is_some_and(|k| Decoded::same_checks(words, &self.words[..k])) {
            self.d.refill(words);
            return Ok(());
        }
        let r = self.d.fill(words, has_y, has_c);
        self.ok_len = None;
        if r.is_ok() {
            if let Some(w) = self.words.get_mut(..words.len()) {
                w.copy_from_slice(words);
                self.ok_len = Some(words.len());
            }
        }
        r
    }

    /// `d` decoded some other way: the next block is filled in full.
    pub fn set(&mut self, d: Decoded) {
        self.d = d;
        self.ok_len = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// What a decoded block says (the values of absent letters are not part of it).
    fn view(d: &Decoded) -> String {
        let letters: Vec<(char, Option<Val>)> = d.letters().map(|l| (l, d.get(l))).collect();
        format!("{:?} {:?} {:?} {:?} {:?}", &d.g[..], &d.m[..], letters, d.comma_c, d.comma_r)
    }

    fn word() -> impl Strategy<Value = (char, bool, Val)> {
        (
            prop::sample::select(vec!['G', 'G', 'M', 'T', 'X', 'Z', 'U', 'W', 'F', 'P', 'D', 'L', 'J', 'C']),
            prop::sample::select(vec![0.0, 1.0, 4.0, 84.0, 98.0, 99.0, 2.5, 101.0, -3.0]),
            any::<bool>(),
            1u32..40,
        )
            .prop_map(|(l, v, decimal, col)| (l, false, Val { v, decimal, col, literal: true }))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        /// Decoding a stream of blocks through one `BlockDecoder` (which only updates the
        /// values of a block shaped like the last) gives, block for block, what a fresh
        /// `Decoded::build` gives: the same decode or the same error.
        #[test]
        fn block_decoder_equals_a_fresh_decode(blocks in prop::collection::vec(
            prop::collection::vec(word(), 1..5), 1..12).prop_flat_map(|b| {
                // Repeat blocks with new values so that same-shape blocks follow each other.
                let n = b.len();
                (Just(b), prop::collection::vec((0..n, 0.0f64..500.0, 1u32..40), 0..12))
            })
        ) {
            let (mut stream, edits) = blocks;
            for (k, v, col) in edits {
                let mut b = stream[k].clone();
                for w in b.iter_mut().filter(|w| matches!(w.0, 'X' | 'Z' | 'U' | 'W' | 'F' | 'C')) {
                    w.2.v = v;
                    w.2.col = col;
                }
                if let Some(w) = b.first_mut() {
                    w.2.col = col;
                }
                stream.insert(k + 1, b);
            }
            let mut bd = BlockDecoder::default();
            for words in &stream {
                let fresh = Decoded::build(words, false, true);
                let got = bd.decode(words, false, true);
                match (&fresh, &got) {
                    (Ok(f), Ok(())) => prop_assert_eq!(view(f), view(&bd.d), "{:?}", words),
                    (Err(a), Err(b)) => prop_assert_eq!(a, b),
                    _ => prop_assert!(false, "{:?}: fresh {:?}, kept {:?}", words, fresh.as_ref().map(view), got),
                }
            }
        }
    }
}
