//! Block parser: one source line → one [`Block`] (NC words or a macro statement).
//!
//! Lexical rules (manual §1, §2.24; Fanuc 0i-TF where the manual is silent):
//! - `( … )` is a comment anywhere; an unclosed `(` is refused (PS0009 at its column): a
//!   comment does not span lines, and a lost `)` would silently hide the words after it.
//! - `;` is the end-of-block character of the manual's listings; the rest of the line after
//!   it is ignored (the manual puts comments there).
//! - Spaces are ignored between tokens (Fanuc ignores them), not inside a number.
//! - Letters may be upper or lower case; they are upper-cased.
//! - `/` at the start of a block (after nothing but spaces) is block skip.
//! - A line holding only `%` marks the start/end of the tape; `O1234` starts a program.
//!
//! Parse errors carry Fanuc PS numbers: 3 too many digits, 4 address not found (a number
//! without an address), 5 no data after address, 6 illegal minus sign, 7 illegal decimal
//! point, 9 improper address/character, 114 macro expression format, 118 bracket nesting
//! over 5, 126 illegal DO/END number, 127 NC and macro statement in one block, 128 illegal
//! sequence number in GOTO.

use super::gcode::Val;

/// A parse error: Fanuc/manual alarm number, 1-based column, message.
#[derive(Clone, Debug, PartialEq)]
pub struct PErr {
    pub number: u32,
    pub col: u32,
    pub message: String,
}

fn perr<T>(number: u32, col: u32, message: impl Into<String>) -> Result<T, PErr> {
    Err(PErr { number, col, message: message.into() })
}

/// Fanuc allows at most 8 significant digits in a numeric word (PS0003).
pub const MAX_DIGITS: usize = 8;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BinOp {
    Add,
    Sub,
    Mul,
    Div,
    Mod,
    And,
    Or,
    Xor,
    Eq,
    Ne,
    Gt,
    Ge,
    Lt,
    Le,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Func {
    Sin,
    Cos,
    Tan,
    Asin,
    Acos,
    Atan,
    Sqrt,
    Abs,
    Round,
    Fix,
    Fup,
    Ln,
    Exp,
    Max,
    Min,
    Bin,
    Bcd,
}

impl Func {
    /// Full names and the manual's two-letter abbreviations (§2.24.2 priority table).
    fn from_name(s: &str) -> Option<Func> {
        Some(match s {
            "SIN" | "SI" => Func::Sin,
            "COS" | "CO" => Func::Cos,
            "TAN" | "TA" => Func::Tan,
            "ASIN" | "AS" => Func::Asin,
            "ACOS" | "AC" => Func::Acos,
            "ATAN" | "AT" => Func::Atan,
            "SQRT" | "SQ" => Func::Sqrt,
            "ABS" | "AB" => Func::Abs,
            "ROUND" | "RO" => Func::Round,
            "FIX" | "FI" => Func::Fix,
            "FUP" | "FU" => Func::Fup,
            "LN" => Func::Ln,
            "EXP" | "EX" => Func::Exp,
            "MAX" => Func::Max,
            "MIN" => Func::Min,
            "BIN" => Func::Bin,
            "BCD" => Func::Bcd,
            _ => return None,
        })
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum Expr {
    /// A literal; `decimal` tells whether it was written with a decimal point.
    Num {
        v: f64,
        decimal: bool,
    },
    /// `#n` / `#[expr]`.
    Var(Box<Expr>),
    Neg(Box<Expr>),
    /// `[ expr ]` — kept so that `[#1]` passes a null through like `#1`.
    Paren(Box<Expr>),
    Bin(BinOp, Box<Expr>, Box<Expr>),
    Call(Func, Vec<Expr>),
}

impl Expr {
    /// True when the value does not depend on variables (can be checked before running).
    pub fn is_literal(&self) -> bool {
        match self {
            Expr::Num { .. } => true,
            Expr::Var(_) => false,
            Expr::Neg(e) | Expr::Paren(e) => e.is_literal(),
            Expr::Bin(_, a, b) => a.is_literal() && b.is_literal(),
            Expr::Call(_, a) => a.iter().all(|e| e.is_literal()),
        }
    }
}

/// One address word. `comma` is set for `,C` / `,R` (chamfer / corner R).
#[derive(Clone, Debug, PartialEq)]
pub struct Word {
    pub letter: char,
    pub comma: bool,
    pub value: Expr,
    pub col: u32,
}

#[derive(Clone, Debug, PartialEq)]
pub enum Stmt {
    /// Nothing to execute (blank, comment only).
    Empty,
    /// A `%` line.
    Percent,
    /// `O1234`: start of a program.
    Program(u32),
    Nc(Vec<Word>),
    Assign {
        var: Expr,
        value: Expr,
    },
    IfGoto {
        cond: Expr,
        target: Expr,
    },
    IfThen {
        cond: Expr,
        var: Expr,
        value: Expr,
    },
    Goto(Expr),
    /// `WHILE [cond] DO n` (cond = Some) or bare `DO n` (infinite loop).
    Do {
        cond: Option<Expr>,
        n: u8,
    },
    End(u8),
    /// A SINUMERIK cycle call (manual 003): `CYCLE81(100,0,1,,25)`, `MCALL CYCLE81(…)`
    /// (`mcall`), or a bare `MCALL` (`name` None) cancelling the modal call. Empty slots
    /// and missing trailing arguments are None.
    /// `cols`: 1-based column of each parameter slot.
    Call {
        mcall: bool,
        name: Option<String>,
        args: Vec<Option<Expr>>,
        cols: Vec<u32>,
    },
}

#[derive(Clone, Debug, PartialEq)]
pub struct Block {
    /// `/` block skip.
    pub skip: bool,
    pub n: Option<u32>,
    pub stmt: Stmt,
    /// Column of the first character of the block (1-based).
    pub col: u32,
}

struct Cur<'a> {
    c: &'a [char],
    i: usize,
    /// Recursion guard for `-`/`#` chains (a hostile line must not overflow the stack).
    nest: u32,
}

const MAX_NEST: u32 = 32;

impl Cur<'_> {
    fn deeper(&mut self) -> Result<(), PErr> {
        self.nest += 1;
        if self.nest > MAX_NEST {
            return perr(114, self.col(), "expression nested too deeply");
        }
        Ok(())
    }
}

impl<'a> Cur<'a> {
    fn skip_ws(&mut self) {
        while self.i < self.c.len() && self.c[self.i].is_whitespace() {
            self.i += 1;
        }
    }
    fn peek(&mut self) -> Option<char> {
        self.skip_ws();
        self.c.get(self.i).copied()
    }
    fn peek_at(&self, k: usize) -> Option<char> {
        self.c.get(self.i + k).copied()
    }
    fn col(&self) -> u32 {
        self.i as u32 + 1
    }
    fn eat(&mut self, ch: char) -> bool {
        if self.peek() == Some(ch) {
            self.i += 1;
            true
        } else {
            false
        }
    }
    /// The run of letters at the cursor (upper-cased), without consuming it.
    fn letters(&mut self) -> Letters {
        self.skip_ws();
        let mut s = Letters { buf: [0; LETTERS_MAX], len: 0 };
        let mut j = self.i;
        while j < self.c.len() && self.c[j].is_ascii_alphabetic() {
            if s.len < LETTERS_MAX {
                s.buf[s.len] = self.c[j].to_ascii_uppercase() as u8;
                s.len += 1;
            }
            j += 1;
        }
        s
    }
    fn at_end(&mut self) -> bool {
        self.peek().is_none()
    }
}

const LETTERS_MAX: usize = 16;

/// A run of address letters / a keyword, upper-cased, kept on the stack (one per word, so a
/// heap string here cost an allocation per address). Longer runs keep their first 16
/// letters, which no keyword or function name reaches.
#[derive(Clone, Copy)]
struct Letters {
    buf: [u8; LETTERS_MAX],
    len: usize,
}

impl Letters {
    fn as_str(&self) -> &str {
        std::str::from_utf8(&self.buf[..self.len]).unwrap_or("")
    }
    fn len(&self) -> usize {
        self.len
    }
    fn first(&self) -> Option<char> {
        (self.len > 0).then(|| self.buf[0] as char)
    }
}

impl std::ops::Deref for Letters {
    type Target = str;
    fn deref(&self) -> &str {
        self.as_str()
    }
}

impl std::fmt::Display for Letters {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl PartialEq<&str> for Letters {
    fn eq(&self, o: &&str) -> bool {
        &self.buf[..self.len] == o.as_bytes()
    }
}

/// Index of the first `\n` in `b`, eight bytes at a time.
pub fn find_newline(b: &[u8]) -> Option<usize> {
    const LO: u64 = 0x0101_0101_0101_0101;
    const HI: u64 = 0x8080_8080_8080_8080;
    let pat = LO * b'\n' as u64;
    let mut i = 0;
    while i + 8 <= b.len() {
        let mut w = [0u8; 8];
        w.copy_from_slice(&b[i..i + 8]);
        let x = u64::from_le_bytes(w) ^ pat;
        // A zero byte of x (a '\n' in the word) sets its high bit here.
        let z = x.wrapping_sub(LO) & !x & HI;
        if z != 0 {
            return Some(i + (z.trailing_zeros() / 8) as usize);
        }
        i += 8;
    }
    b[i..].iter().position(|&c| c == b'\n').map(|k| i + k)
}

/// Remove comments: `( … )` becomes spaces (columns stay right), `;` ends the line. A `(`
/// left open at the end of the line is refused: a comment never spans lines, and an open one
/// usually means a `)` was lost, which would hide the words meant to follow it.
fn strip(line: &str) -> Result<Vec<char>, PErr> {
    let mut out = Vec::with_capacity(line.len());
    let mut open = None;
    for ch in line.chars() {
        if open.is_some() {
            if ch == ')' {
                open = None;
            }
            out.push(' ');
        } else if ch == '(' {
            open = Some(out.len() as u32 + 1);
            out.push(' ');
        } else if ch == ';' {
            break;
        } else {
            out.push(ch);
        }
    }
    match open {
        Some(col) => perr(9, col, "this comment is not closed: add `)` at its end (a comment ends on its own line)"),
        None => Ok(out),
    }
}

pub fn parse_line(line: &str) -> Result<Block, PErr> {
    if let Some(b) = fast_line(line) {
        return Ok(b);
    }
    if let Some(b) = cycle_call(line) {
        return b;
    }
    let chars = strip(line)?;
    let mut c = Cur { c: &chars, i: 0, nest: 0 };
    let first = c.peek();
    let col = c.col();
    let mut b = Block { skip: false, n: None, stmt: Stmt::Empty, col };
    match first {
        None => return Ok(b),
        Some('%') => {
            c.i += 1;
            if !c.at_end() {
                return perr(9, c.col(), "nothing may follow `%` on its line");
            }
            b.stmt = Stmt::Percent;
            return Ok(b);
        }
        _ => {}
    }
    if c.eat('/') {
        b.skip = true;
        // `/n` (skip switch n) is accepted like `/`.
        if matches!(c.peek(), Some('1'..='9')) && !matches!(c.peek_at(1), Some('0'..='9' | '.')) {
            c.i += 1;
        }
    }
    // Program number.
    if matches!(c.peek(), Some('O' | 'o')) && !c.peek_at(1).is_some_and(|x| x.is_ascii_alphabetic()) {
        let wcol = c.col();
        c.i += 1;
        let (v, dec) = number(&mut c, 'O', wcol)?;
        if dec {
            return perr(7, wcol, "a program number takes no decimal point (O1234)");
        }
        if !c.at_end() {
            return perr(9, c.col(), "an O program number must be alone in its block");
        }
        if !(0.0..=9999.0).contains(&v) {
            return perr(3, wcol, "program numbers are O0000–O9999");
        }
        b.stmt = Stmt::Program(v as u32);
        return Ok(b);
    }
    // Sequence number.
    if matches!(c.peek(), Some('N' | 'n')) && !c.peek_at(1).is_some_and(|x| x.is_ascii_alphabetic()) {
        let wcol = c.col();
        c.i += 1;
        if c.peek() == Some('-') {
            return perr(6, c.col(), "a sequence number cannot be negative");
        }
        let (v, dec) = number(&mut c, 'N', wcol)?;
        if dec {
            return perr(7, wcol, "a sequence number takes no decimal point (N10)");
        }
        if v > 99999.0 {
            return perr(3, wcol, "sequence numbers are N1–N99999");
        }
        b.n = Some(v as u32);
    }
    if c.at_end() {
        return Ok(b);
    }
    let kw = c.letters();
    let kcol = c.col();
    b.stmt = if c.peek() == Some('#') {
        let (var, value) = assignment(&mut c)?;
        Stmt::Assign { var, value }
    } else if kw == "IF" {
        c.i += 2;
        let cond = condition(&mut c)?;
        let k = c.letters();
        if k == "GOTO" {
            c.i += 4;
            Stmt::IfGoto { cond, target: goto_target(&mut c)? }
        } else if k == "THEN" {
            c.i += 4;
            if c.peek() != Some('#') {
                return perr(114, c.col(), "THEN must be followed by an assignment #i=…");
            }
            let (var, value) = assignment(&mut c)?;
            Stmt::IfThen { cond, var, value }
        } else {
            return perr(114, c.col(), "IF [condition] must be followed by GOTO n or THEN #i=…");
        }
    } else if kw == "WHILE" {
        c.i += 5;
        let cond = condition(&mut c)?;
        if c.letters() != "DO" {
            return perr(114, c.col(), "WHILE [condition] must be followed by DO n");
        }
        c.i += 2;
        Stmt::Do { cond: Some(cond), n: loop_number(&mut c)? }
    } else if kw == "GOTO" {
        c.i += 4;
        Stmt::Goto(goto_target(&mut c)?)
    } else if kw == "DO" {
        c.i += 2;
        Stmt::Do { cond: None, n: loop_number(&mut c)? }
    } else if kw == "END" {
        c.i += 3;
        Stmt::End(loop_number(&mut c)?)
    } else {
        let _ = kcol;
        Stmt::Nc(words(&mut c)?)
    };
    if !c.at_end() {
        return perr(127, c.col(), "a macro statement must be alone in its block (no NC words after it)");
    }
    Ok(b)
}

/// Most arguments of one cycle call (SINUMERIK's longest, CYCLE84, has about 30).
pub const MAX_CALL_ARGS: usize = 40;

/// `[N…] [MCALL] CYCLEnn(args)` or `[N…] MCALL`: parsed before comment stripping, since the
/// argument list is in parentheses. None when the line is not a cycle call.
fn cycle_call(line: &str) -> Option<Result<Block, PErr>> {
    let chars: Vec<char> = line.chars().collect();
    let mut i = 0;
    let ws = |i: &mut usize| {
        while *i < chars.len() && chars[*i].is_whitespace() {
            *i += 1;
        }
    };
    ws(&mut i);
    let col = i as u32 + 1;
    let mut n = None;
    if matches!(chars.get(i), Some('N' | 'n')) && chars.get(i + 1).is_some_and(|c| c.is_ascii_digit()) {
        let start = i + 1;
        i += 1;
        while i < chars.len() && chars[i].is_ascii_digit() {
            i += 1;
        }
        let v: String = chars[start..i].iter().collect();
        n = v.parse::<u32>().ok().filter(|v| *v <= 99999);
        n?;
        ws(&mut i);
    }
    let word = |i: usize| -> String { chars[i..].iter().take_while(|c| c.is_ascii_alphanumeric()).collect::<String>().to_ascii_uppercase() };
    let mut w = word(i);
    let mut mcall = false;
    if w == "MCALL" {
        mcall = true;
        i += 5;
        ws(&mut i);
        w = word(i);
        let rest_empty = |j: usize| chars[j..].iter().all(|c| c.is_whitespace()) || chars.get(j) == Some(&';');
        if w.is_empty() && rest_empty(i) {
            return Some(Ok(Block { skip: false, n, stmt: Stmt::Call { mcall, name: None, args: Vec::new(), cols: Vec::new() }, col }));
        }
    }
    if !(w.starts_with("CYCLE") && w.len() > 5) {
        return if mcall { Some(perr(9, i as u32 + 1, "MCALL is followed by a cycle call CYCLEnn(…) or nothing")) } else { None };
    }
    let name_col = i as u32 + 1;
    i += w.len();
    ws(&mut i);
    if chars.get(i) != Some(&'(') {
        return Some(perr(9, i as u32 + 1, format!("{w}: the parameters follow in parentheses: {w}(…)")));
    }
    i += 1;
    // Split at top-level commas up to the matching ')'.
    let mut args = Vec::new();
    let mut depth = 0i32;
    let mut start = i;
    let close;
    loop {
        match chars.get(i) {
            None => return Some(perr(9, i as u32 + 1, format!("{w}(: missing `)`"))),
            Some('[') => depth += 1,
            Some(']') => depth -= 1,
            Some(',') if depth == 0 => {
                args.push((start, i));
                start = i + 1;
            }
            Some(')') if depth == 0 => {
                args.push((start, i));
                close = i;
                break;
            }
            _ => {}
        }
        i += 1;
    }
    if args.len() > MAX_CALL_ARGS {
        return Some(perr(9, name_col, format!("{w}: more than {MAX_CALL_ARGS} parameters")));
    }
    let mut out = Vec::new();
    let mut cols = Vec::new();
    for (a, b) in args {
        let lead = chars[a..b].iter().take_while(|c| c.is_whitespace()).count();
        cols.push((a + lead) as u32 + 1);
        let text = &chars[a..b];
        if text.iter().all(|c| c.is_whitespace()) {
            out.push(None);
            continue;
        }
        // Parse the argument with the expression parser, columns kept.
        let mut padded: Vec<char> = vec![' '; a];
        padded.extend_from_slice(text);
        let mut c = Cur { c: &padded, i: a, nest: 0 };
        let e = match expr(&mut c, 1) {
            Ok(e) => e,
            Err(e) => return Some(Err(e)),
        };
        if !c.at_end() {
            return Some(perr(9, c.col(), format!("{w}: parameter {}: unexpected `{}`", out.len() + 1, padded[c.i])));
        }
        out.push(Some(e));
    }
    // Trailing empty slots carry nothing.
    while out.last().is_some_and(|a| a.is_none()) {
        out.pop();
    }
    cols.truncate(out.len());
    let mut j = close + 1;
    ws(&mut j);
    match chars.get(j) {
        None | Some(';') => {}
        // A comment may follow.
        Some('(') => {}
        Some(c) => return Some(perr(9, j as u32 + 1, format!("`{c}` after the cycle call: a cycle call stands alone in its block"))),
    }
    Some(Ok(Block { skip: false, n, stmt: Stmt::Call { mcall, name: Some(w), args: out, cols }, col }))
}

fn is_keyword(s: &str) -> bool {
    ["IF", "WHILE", "GOTO", "DO", "END", "THEN"].iter().any(|k| s.starts_with(k))
}

fn words(c: &mut Cur) -> Result<Vec<Word>, PErr> {
    let mut out = Vec::new();
    while let Some(ch) = c.peek() {
        let col = c.col();
        let comma = ch == ',';
        if comma {
            c.i += 1;
            let l = c.peek();
            if !matches!(l, Some('C' | 'c' | 'R' | 'r')) {
                return perr(9, col, "after `,` only C (chamfer) or R (corner radius) may follow");
            }
        } else if ch == '#' {
            return perr(127, col, "a macro statement cannot share a block with NC words");
        } else if ch.is_ascii_digit() || ch == '-' || ch == '+' || ch == '.' {
            return perr(4, col, format!("`{ch}` without an address letter; write e.g. X{ch}…"));
        } else if !ch.is_ascii_alphabetic() {
            return perr(9, col, format!("improper character `{}`", ch.escape_default()));
        }
        let run = c.letters();
        if run.len() > 1 {
            if is_keyword(&run) {
                return perr(127, col, format!("{run}: a macro statement cannot share a block with NC words"));
            }
            return perr(9, col, format!("improper address `{run}`: an address is one letter followed by a value"));
        }
        let letter = run.first().unwrap_or('?');
        c.i += 1;
        let value = word_value(c, letter, col)?;
        if matches!(letter, 'G' | 'M' | 'N' | 'O' | 'T' | 'L') {
            if let Expr::Neg(_) = value {
                return perr(6, col, format!("{letter} cannot take a minus sign"));
            }
        }
        if letter == 'N' {
            return perr(9, col, "a sequence number N must stand at the start of the block");
        }
        if letter == 'O' {
            return perr(9, col, "an O program number must be alone in its block");
        }
        out.push(Word { letter, comma, value, col });
    }
    Ok(out)
}

/// The value after an address: a number, `#var`, `[expr]`, optionally signed.
fn word_value(c: &mut Cur, letter: char, col: u32) -> Result<Expr, PErr> {
    let neg = if c.eat('-') {
        true
    } else {
        c.eat('+');
        false
    };
    let e = match c.peek() {
        Some('#') => {
            c.i += 1;
            c.deeper()?;
            let e = primary(c, 1)?;
            c.nest -= 1;
            Expr::Var(Box::new(e))
        }
        Some('[') => {
            c.i += 1;
            let e = expr(c, 1)?;
            if !c.eat(']') {
                return perr(114, c.col(), "missing `]`");
            }
            Expr::Paren(Box::new(e))
        }
        Some(ch) if ch.is_ascii_digit() || ch == '.' => {
            let (v, decimal) = number(c, letter, col)?;
            Expr::Num { v, decimal }
        }
        _ => return perr(5, col, format!("no value after address {letter}")),
    };
    Ok(if neg { Expr::Neg(Box::new(e)) } else { e })
}

/// Digits with an optional decimal point, contiguous (no spaces inside).
fn number(c: &mut Cur, letter: char, col: u32) -> Result<(f64, bool), PErr> {
    c.skip_ws();
    let start = c.i;
    let mut decimal = false;
    while let Some(ch) = c.c.get(c.i) {
        if ch.is_ascii_digit() {
            c.i += 1;
        } else if *ch == '.' && !decimal {
            decimal = true;
            c.i += 1;
        } else {
            break;
        }
    }
    let digits = &c.c[start..c.i];
    if digits.is_empty() || digits == ['.'] {
        return perr(5, col, format!("no value after address {letter}"));
    }
    // Significant digits: without leading zeros, and without trailing zeros after a point.
    let lead = digits.iter().take_while(|ch| matches!(ch, '0' | '.')).count();
    let rest = digits[lead..].iter().filter(|ch| **ch != '.');
    let mut sig = rest.clone().count();
    if decimal {
        sig -= rest.rev().take_while(|ch| **ch == '0').count();
    }
    if sig > MAX_DIGITS {
        // A runaway token (a 2 MB number) is named by its start and length, not echoed whole.
        let s: String = if digits.len() > 20 {
            format!("{}… ({} characters)", digits[..12].iter().collect::<String>(), digits.len())
        } else {
            digits.iter().collect()
        };
        return perr(3, col, format!("{letter}{s}: more than {MAX_DIGITS} digits"));
    }
    if let Some(v) = fast_decimal(digits) {
        return Ok((v, decimal));
    }
    if digits.len() > 62 {
        // Many leading zeros: rare, parse through a heap string.
        let mut s: String = digits.iter().collect();
        if s.ends_with('.') {
            s.push('0');
        }
        return Ok((s.parse().unwrap_or(0.0), decimal));
    }
    // Parse from a stack buffer (digits and '.' are ASCII); `5.` gets a 0 appended.
    let mut buf = [0u8; 64];
    let mut n = 0;
    for ch in digits {
        if n < buf.len() - 1 {
            buf[n] = *ch as u8;
            n += 1;
        }
    }
    if buf[n - 1] == b'.' {
        buf[n] = b'0';
        n += 1;
    }
    let v: f64 = std::str::from_utf8(&buf[..n]).ok().and_then(|t| t.parse().ok()).unwrap_or(0.0);
    Ok((v, decimal))
}

/// Most words a block may have to take the fast path ([`fast_words`]); longer blocks go
/// through the full parser.
pub const FAST_WORDS: usize = 24;

/// One evaluated word as [`crate::interp::gcode::Decoded::build`] takes it: letter, `,`
/// (always false here), value.
pub type FastWord = (char, bool, Val);

/// An empty [`FastWord`] to initialise a buffer with.
pub const NO_WORD: FastWord = ('\0', false, Val { v: 0.0, decimal: false, col: 0, literal: true });

/// What [`fast_words`] found besides the words.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FastBlock {
    pub n: Option<u32>,
    /// Column of the first character of the block (1-based).
    pub col: u32,
    /// Number of words written to the buffer (0: a blank line or `N…` alone).
    pub len: usize,
    /// Where the `;` comment starts (the line length without one): the bytes before it
    /// are ASCII, the ones after it are not looked at.
    pub comment: usize,
}

/// The common case of CAM output, parsed straight from the bytes into `out` without any
/// allocation: an ASCII line of `[N…] LETTER number …` words (plain numbers, optional sign,
/// at most [`FAST_WORDS`]), optionally ending in a `;` comment, or a blank line. Anything
/// else (comments in parentheses, macros, `/`, `O`, `%`, `,C`, any error) returns `None`
/// and goes through the full parser, so both give the same block except that a negative
/// number is `-x` here instead of `Neg(Num { v: x })`, which evaluates the same.
pub fn fast_words(line: &[u8], out: &mut [FastWord; FAST_WORDS]) -> Option<FastBlock> {
    words_from_bytes::<true>(line, out)
}

/// [`fast_words`] for the static check: only the values that the checks of
/// [`crate::interp::gcode::Decoded::build`] look at (G, M, P, N) are computed; the other
/// words carry their digits unscaled.
pub fn fast_words_static(line: &[u8], out: &mut [FastWord; FAST_WORDS]) -> Option<FastBlock> {
    words_from_bytes::<false>(line, out)
}

fn words_from_bytes<const VALUES: bool>(line: &[u8], out: &mut [FastWord; FAST_WORDS]) -> Option<FastBlock> {
    let b = line;
    let end = b.len();
    let ws = |c: u8| matches!(c, b' ' | b'\t' | b'\r' | b'\n');
    let mut i = 0;
    while i < end && ws(b[i]) {
        i += 1;
    }
    let col = i as u32 + 1;
    let mut n = None;
    let mut len = 0;
    loop {
        while i < end && ws(b[i]) {
            i += 1;
        }
        if i >= end || b[i] == b';' {
            break;
        }
        let wcol = i as u32 + 1;
        // ASCII letters only (clearing bit 5 maps a–z onto A–Z and nothing else onto them).
        let letter = b[i] & !0x20;
        if !letter.is_ascii_uppercase() || letter == b'O' {
            return None;
        }
        i += 1;
        let mut neg = false;
        let signed = i < end && (b[i] == b'-' || b[i] == b'+');
        if signed {
            neg = b[i] == b'-';
            i += 1;
        }
        // Integer digits, then after a point the fraction's: one mantissa. Wrapping
        // arithmetic: more than 15 digits leave for the full parser below.
        let start = i;
        let mut mant = 0u64;
        while i < end && b[i].wrapping_sub(b'0') < 10 {
            mant = mant.wrapping_mul(10).wrapping_add(u64::from(b[i] - b'0'));
            i += 1;
        }
        let mut frac = 0;
        let decimal = i < end && b[i] == b'.';
        if decimal {
            i += 1;
            let f0 = i;
            while i < end && b[i].wrapping_sub(b'0') < 10 {
                mant = mant.wrapping_mul(10).wrapping_add(u64::from(b[i] - b'0'));
                i += 1;
            }
            frac = i - f0;
        }
        let nd = i - start - decimal as usize;
        // Letters must be followed by a number and then a separator or the next letter.
        if nd == 0 || nd > 15 || (i < end && !(b[i].is_ascii_alphabetic() || ws(b[i]) || b[i] == b';')) {
            return None;
        }
        // A sign on a code or a sequence number is the full parser's to judge (N+0 is no
        // sequence number there).
        if signed && matches!(letter, b'G' | b'M' | b'N' | b'T' | b'L') {
            return None;
        }
        // As in `number`: significant digits exclude leading zeros and, with a point,
        // trailing zeros; only counted when there are more digits than the limit.
        if nd > MAX_DIGITS && significant(&b[start..i], decimal) > MAX_DIGITS {
            return None;
        }
        let v = if VALUES || matches!(letter, b'G' | b'M' | b'P' | b'N') { mant as f64 / *POW10.get(frac)? } else { mant as f64 };
        if letter == b'N' {
            if len > 0 || n.is_some() || decimal || v > 99999.0 {
                return None;
            }
            n = Some(v as u32);
            continue;
        }
        let v = if neg { -v } else { v };
        *out.get_mut(len)? = (letter as char, false, Val { v, decimal, col: wcol, literal: true });
        len += 1;
    }
    Some(FastBlock { n, col, len, comment: i })
}

/// Significant digits of an ASCII number (digits and at most one '.'), counted as
/// [`number`] counts them.
fn significant(digits: &[u8], decimal: bool) -> usize {
    let lead = digits.iter().take_while(|c| matches!(c, b'0' | b'.')).count();
    let rest = digits[lead..].iter().filter(|c| **c != b'.');
    let sig = rest.clone().count();
    if decimal {
        sig - rest.rev().take_while(|c| **c == b'0').count()
    } else {
        sig
    }
}

/// [`fast_words`] as a [`Block`] (a blank line is left to the full parser).
fn fast_line(line: &str) -> Option<Block> {
    let mut buf = [NO_WORD; FAST_WORDS];
    let fb = fast_words(line.as_bytes(), &mut buf)?;
    if fb.len == 0 && fb.n.is_none() {
        return None;
    }
    let words: Vec<Word> = buf[..fb.len]
        .iter()
        .map(|&(letter, _, v)| Word { letter, comma: false, value: Expr::Num { v: v.v, decimal: v.decimal }, col: v.col })
        .collect();
    let stmt = if words.is_empty() { Stmt::Empty } else { Stmt::Nc(words) };
    Some(Block { skip: false, n: fb.n, stmt, col: fb.col })
}

/// Exact powers of ten (10^22 is the largest exactly representable one).
const POW10: [f64; 23] =
    [1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22];

/// `digits` (ASCII digits and at most one '.') as an f64 without going through a string:
/// an integer mantissa of at most 15 digits divided by an exact power of ten is correctly
/// rounded, so the result equals `str::parse`. `None` when that does not hold.
fn fast_decimal(digits: &[char]) -> Option<f64> {
    let mut mant: u64 = 0;
    let mut nd = 0; // digits in the mantissa, leading zeros excluded
    let mut frac = 0usize;
    let mut point = false;
    for &ch in digits {
        if ch == '.' {
            point = true;
            continue;
        }
        let d = ch.to_digit(10)? as u64;
        if mant != 0 || d != 0 {
            nd += 1;
        }
        if nd > 15 {
            return None;
        }
        mant = mant * 10 + d;
        if point {
            frac += 1;
        }
    }
    Some(mant as f64 / *POW10.get(frac)?)
}

fn assignment(c: &mut Cur) -> Result<(Expr, Expr), PErr> {
    let col = c.col();
    if !c.eat('#') {
        return perr(114, col, "expected #variable");
    }
    let var = primary(c, 0)?;
    if !c.eat('=') {
        return perr(114, c.col(), "expected `=` after the variable (#i=expression)");
    }
    if c.at_end() {
        return perr(114, c.col(), "missing expression after `=`");
    }
    let value = expr(c, 0)?;
    Ok((var, value))
}

fn condition(c: &mut Cur) -> Result<Expr, PErr> {
    if c.peek() != Some('[') {
        return perr(114, c.col(), "the condition must be enclosed in [ ] (e.g. IF [#1 GT 0] …)");
    }
    primary(c, 0)
}

fn goto_target(c: &mut Cur) -> Result<Expr, PErr> {
    let col = c.col();
    if c.at_end() {
        return perr(128, col, "GOTO needs a sequence number 1–99999");
    }
    let e = expr(c, 0)?;
    if let Expr::Num { v, decimal } = e {
        if decimal || !(1.0..=99999.0).contains(&v) {
            return perr(128, col, format!("GOTO {v}: the sequence number must be an integer 1–99999"));
        }
    }
    Ok(e)
}

fn loop_number(c: &mut Cur) -> Result<u8, PErr> {
    let col = c.col();
    let n = match c.peek() {
        Some(d) if d.is_ascii_digit() => number(c, 'n', col)?,
        _ => return perr(126, col, "DO/END need a loop number 1, 2 or 3"),
    };
    if n.1 || !(1.0..=3.0).contains(&n.0) {
        return perr(126, col, format!("loop number {}: DO/END numbers are 1, 2 or 3", n.0));
    }
    Ok(n.0 as u8)
}

/// Expression with comparisons (lowest), `+ - OR XOR`, `* / AND MOD`, unary, primary.
fn expr(c: &mut Cur, depth: u32) -> Result<Expr, PErr> {
    let a = sum(c, depth)?;
    let op = match c.peek() {
        Some('=') if c.peek_at(1) == Some('=') => Some((BinOp::Eq, 2)),
        Some('<') if c.peek_at(1) == Some('>') => Some((BinOp::Ne, 2)),
        Some('>') if c.peek_at(1) == Some('=') => Some((BinOp::Ge, 2)),
        Some('<') if c.peek_at(1) == Some('=') => Some((BinOp::Le, 2)),
        Some('>') => Some((BinOp::Gt, 1)),
        Some('<') => Some((BinOp::Lt, 1)),
        _ => match c.letters().as_str() {
            "EQ" => Some((BinOp::Eq, 2)),
            "NE" => Some((BinOp::Ne, 2)),
            "GT" => Some((BinOp::Gt, 2)),
            "GE" => Some((BinOp::Ge, 2)),
            "LT" => Some((BinOp::Lt, 2)),
            "LE" => Some((BinOp::Le, 2)),
            _ => None,
        },
    };
    if let Some((op, len)) = op {
        c.i += len;
        let b = sum(c, depth)?;
        return Ok(Expr::Bin(op, Box::new(a), Box::new(b)));
    }
    Ok(a)
}

fn sum(c: &mut Cur, depth: u32) -> Result<Expr, PErr> {
    let mut a = term(c, depth)?;
    loop {
        let op = match c.peek() {
            Some('+') => (BinOp::Add, 1),
            Some('-') => (BinOp::Sub, 1),
            _ => match c.letters().as_str() {
                "OR" => (BinOp::Or, 2),
                "XOR" => (BinOp::Xor, 3),
                _ => return Ok(a),
            },
        };
        c.i += op.1;
        let b = term(c, depth)?;
        a = Expr::Bin(op.0, Box::new(a), Box::new(b));
    }
}

fn term(c: &mut Cur, depth: u32) -> Result<Expr, PErr> {
    let mut a = unary(c, depth)?;
    loop {
        let op = match c.peek() {
            Some('*') => (BinOp::Mul, 1),
            Some('/') => (BinOp::Div, 1),
            _ => match c.letters().as_str() {
                "AND" => (BinOp::And, 3),
                "AN" => (BinOp::And, 2),
                "MOD" => (BinOp::Mod, 3),
                _ => return Ok(a),
            },
        };
        c.i += op.1;
        let b = unary(c, depth)?;
        a = Expr::Bin(op.0, Box::new(a), Box::new(b));
    }
}

fn unary(c: &mut Cur, depth: u32) -> Result<Expr, PErr> {
    c.deeper()?;
    let r = if c.eat('-') {
        unary(c, depth).map(|e| Expr::Neg(Box::new(e)))
    } else if c.eat('+') {
        unary(c, depth)
    } else {
        primary(c, depth)
    };
    c.nest -= 1;
    r
}

/// Fanuc allows brackets nested five deep (PS0118 beyond).
const MAX_BRACKETS: u32 = 5;

fn primary(c: &mut Cur, depth: u32) -> Result<Expr, PErr> {
    let col = c.col();
    match c.peek() {
        Some('[') => {
            if depth >= MAX_BRACKETS {
                return perr(118, col, format!("brackets nested deeper than {MAX_BRACKETS}"));
            }
            c.i += 1;
            let e = expr(c, depth + 1)?;
            if !c.eat(']') {
                return perr(114, c.col(), "missing `]`");
            }
            Ok(Expr::Paren(Box::new(e)))
        }
        Some('#') => {
            c.i += 1;
            c.deeper()?;
            let e = primary(c, depth)?;
            c.nest -= 1;
            Ok(Expr::Var(Box::new(e)))
        }
        Some(ch) if ch.is_ascii_digit() || ch == '.' => {
            let (v, decimal) = number(c, '#', col)?;
            Ok(Expr::Num { v, decimal })
        }
        Some(ch) if ch.is_ascii_alphabetic() => {
            let name = c.letters();
            let Some(f) = Func::from_name(&name) else {
                return perr(114, col, format!("unknown function or operator `{name}`"));
            };
            c.i += name.len();
            if c.peek() != Some('[') {
                return perr(114, c.col(), format!("{name} needs its argument in [ ]"));
            }
            if depth >= MAX_BRACKETS {
                return perr(118, c.col(), format!("brackets nested deeper than {MAX_BRACKETS}"));
            }
            c.i += 1;
            let mut args = vec![expr(c, depth + 1)?];
            while c.eat(',') {
                args.push(expr(c, depth + 1)?);
            }
            if !c.eat(']') {
                return perr(114, c.col(), "missing `]`");
            }
            // ATAN[a]/[b] (the manual's two-side form).
            if f == Func::Atan && args.len() == 1 && c.peek() == Some('/') {
                let save = c.i;
                c.i += 1;
                if c.peek() == Some('[') {
                    c.i += 1;
                    args.push(expr(c, depth + 1)?);
                    if !c.eat(']') {
                        return perr(114, c.col(), "missing `]`");
                    }
                } else {
                    c.i = save;
                }
            }
            let want = match f {
                Func::Max | Func::Min => 2..=2,
                Func::Atan => 1..=2,
                _ => 1..=1,
            };
            if !want.contains(&args.len()) {
                return perr(114, col, format!("{name} takes {} argument(s), got {}", want.end(), args.len()));
            }
            Ok(Expr::Call(f, args))
        }
        Some(ch) => perr(114, col, format!("unexpected `{ch}` in expression")),
        None => perr(114, col, "expression ends too early"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn nc(s: &str) -> Vec<Word> {
        match parse_line(s).unwrap().stmt {
            Stmt::Nc(w) => w,
            other => panic!("{other:?}"),
        }
    }

    type Norm = (Option<u32>, u32, Vec<(char, u32, Expr)>);

    /// A block as comparable data: a negative number as `-x` (the fast path's form).
    fn norm(b: Block) -> Norm {
        match b.stmt {
            Stmt::Nc(w) => (
                b.n,
                b.col,
                w.into_iter()
                    .map(|w| {
                        let v = match w.value {
                            Expr::Neg(e) => match *e {
                                Expr::Num { v, decimal } => Expr::Num { v: -v, decimal },
                                e => Expr::Neg(Box::new(e)),
                            },
                            e => e,
                        };
                        (w.letter, w.col, v)
                    })
                    .collect::<Vec<_>>(),
            ),
            other => (b.n, b.col, vec![('?', 0, Expr::Num { v: if other == Stmt::Empty { 0.0 } else { 1.0 }, decimal: false })]),
        }
    }

    /// The block of `t` through the full parser (the fast path bypassed: a `(x)` comment
    /// before any `;` forces it).
    fn slow_line(t: &str) -> Result<Block, PErr> {
        match t.find(';') {
            Some(k) => parse_line(&format!("{}(x){}", &t[..k], &t[k..])),
            None => parse_line(&format!("{t}(x)")),
        }
    }

    /// The byte fast path and the full parser agree on every line the fast path takes.
    #[test]
    fn fast_path_agrees_with_the_full_parser() {
        for t in [
            "G1 X20.000 Z-0.000 F100",
            "  n10 g01 x-.5 z+3 f.2 ; comment",
            "N10",
            "G00X40Z5",
            "X10. U-2.5 W0 ",
            "M03 S1200\r",
            "T0101 G0 X100 Z50",
            "G1 X1.0000000",
            "N99999 G4 P500",
            "X100.000000 Z12345678. W-0012345.6780",
        ] {
            let fast = fast_line(t).unwrap_or_else(|| panic!("fast path should take {t:?}"));
            // The full parser, with the fast path bypassed: `(x)` comment forces it.
            let slow = slow_line(t).expect(t);
            assert_eq!(norm(fast), norm(slow), "{t}");
        }
        for t in [
            "",
            "   ",
            "G-1",
            "X",
            "X.",
            "X1-2",
            "XX1",
            "O10",
            "N1.5",
            "N+0",
            "G+1",
            "G1 N10",
            "X123456789",
            "X1234567891.",
            "X1.2345678912345678",
            "/X1",
            "X1 (c)",
            "#1=2",
            "G1 ,C1",
            "X[1]",
            "X 10",
            "IF",
            "X1é",
        ] {
            assert!(fast_line(t).is_none(), "{t:?} must take the full parser");
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(2000))]
        /// Lines of random NC-like pieces: whatever the fast path takes, the full parser
        /// reads the same (numbers bit for bit), and the fast path takes no line the full
        /// parser rejects.
        #[test]
        fn fast_path_agrees_with_the_full_parser_on_random_lines(
            parts in proptest::collection::vec(
                proptest::prop_oneof![
                    proptest::sample::select(vec!["G", "g", "X", "Z", "U", "w", "F", "M", "N", "T", "P", "O", "L"]),
                    proptest::sample::select(vec!["-", "+", ".", " ", "\t", ";", "0", "00", "1", "5", "9", "12", "250", "000000", "123456789", "99999", "é", "(", "#"]),
                    proptest::sample::select(vec!["20.05", ".007", "3.14159", "1.", "0.30000000", "12.250", "1234567.8", "0.0000001", "7.5"]),
                ],
                0..14,
            )
        ) {
            let t: String = parts.concat();
            let mut ev = [NO_WORD; FAST_WORDS];
            let fast = fast_words(t.as_bytes(), &mut ev);
            let slow = slow_line(&t);
            if let Some(fb) = fast {
                let slow = slow.map_err(|e| format!("{t:?}: fast path took it, full parser: {}", e.message));
                proptest::prop_assert!(slow.is_ok(), "{}", slow.err().unwrap_or_default());
                if fb.len > 0 || fb.n.is_some() {
                    let fast = fast_line(&t).map(norm);
                    let slow = slow_line(&t).ok().map(norm);
                    proptest::prop_assert_eq!(format!("{fast:?}"), format!("{slow:?}"), "{:?}", t);
                }
            }
        }
    }

    #[test]
    fn numbers_parse_without_allocating_the_same_values() {
        let v = |t: &str| match parse_line(t).expect(t).stmt {
            Stmt::Nc(w) => match &w[0].value {
                Expr::Num { v, decimal } => (*v, *decimal),
                Expr::Neg(e) => match **e {
                    Expr::Num { v, decimal } => (-v, decimal),
                    _ => panic!("{t}"),
                },
                _ => panic!("{t}"),
            },
            _ => panic!("{t}"),
        };
        assert_eq!(v("X5."), (5.0, true));
        assert_eq!(v("X.5"), (0.5, true));
        assert_eq!(v("X-12.250"), (-12.25, true));
        assert_eq!(v("X12345678"), (12345678.0, false));
        assert_eq!(v("X1234567.8000"), (1234567.8, true));
        assert_eq!(v(&format!("X{}15", "0".repeat(100))), (15.0, false));
        assert_eq!(v(&format!("X{}1.", "0".repeat(100))), (1.0, true));
        assert_eq!(parse_line("X123456789").unwrap_err().number, 3);
        assert_eq!(parse_line("X1.23456789").unwrap_err().number, 3);
        assert_eq!(parse_line("X.").unwrap_err().number, 5);
        // The fast path agrees with str::parse, bit for bit.
        for t in ["0.1", "20.05", "1234567.8", "0.0000001", "99999999", "3.14159265", "0.30000000", "7.", ".007"] {
            let chars: Vec<char> = t.chars().collect();
            let want: f64 = if t.ends_with('.') { format!("{t}0") } else { t.to_string() }.parse().expect(t);
            assert_eq!(fast_decimal(&chars).map(f64::to_bits), Some(want.to_bits()), "{t}");
        }
    }

    #[test]
    fn words_comments_and_columns() {
        let b = parse_line("N10 G01 X20.5 (cut) Z-3 F.2; tail (x)").unwrap();
        assert_eq!(b.n, Some(10));
        let Stmt::Nc(w) = b.stmt else { panic!() };
        let l: Vec<char> = w.iter().map(|w| w.letter).collect();
        assert_eq!(l, vec!['G', 'X', 'Z', 'F']);
        assert_eq!(w[1].col, 9);
        assert_eq!(w[1].value, Expr::Num { v: 20.5, decimal: true });
        assert_eq!(w[2].value, Expr::Neg(Box::new(Expr::Num { v: 3.0, decimal: false })));
        assert_eq!(w[3].value, Expr::Num { v: 0.2, decimal: true });
    }

    #[test]
    fn compact_and_lower_case_forms() {
        let w = nc("g0x20.z-25.");
        assert_eq!(w.len(), 3);
        assert_eq!(w[1].letter, 'X');
        let b = parse_line("N10G01X-#1").unwrap();
        assert_eq!(b.n, Some(10));
        assert_eq!(parse_line("O0001(NAME)").unwrap().stmt, Stmt::Program(1));
        assert!(matches!(parse_line("GOTO10").unwrap().stmt, Stmt::Goto(_)));
        assert!(matches!(parse_line("#[#2]=3").unwrap().stmt, Stmt::Assign { .. }));
        assert!(matches!(parse_line("WHILE[#1LT10]DO1").unwrap().stmt, Stmt::Do { n: 1, .. }));
        assert!(matches!(parse_line("IF [#1 GT 0] GOTO #2").unwrap().stmt, Stmt::IfGoto { .. }));
        let b = parse_line("/ G00 X1").unwrap();
        assert!(b.skip);
        assert_eq!(parse_line("N5").unwrap().stmt, Stmt::Empty);
        assert_eq!(parse_line("%").unwrap().stmt, Stmt::Percent);
    }

    #[test]
    fn macro_statements() {
        assert!(matches!(parse_line("#1=#2+3*SIN[30]").unwrap().stmt, Stmt::Assign { .. }));
        assert!(matches!(parse_line("IF [#1 EQ 2] GOTO 10").unwrap().stmt, Stmt::IfGoto { .. }));
        assert!(matches!(parse_line("IF[#1<>#2]THEN#3=1").unwrap().stmt, Stmt::IfThen { .. }));
        assert_eq!(
            parse_line("WHILE [#1 LE 3] DO 2").unwrap().stmt,
            match parse_line("WHILE[#1LE3]DO2").unwrap().stmt {
                s @ Stmt::Do { n: 2, .. } => s,
                o => panic!("{o:?}"),
            }
        );
        assert_eq!(parse_line("END 1").unwrap().stmt, Stmt::End(1));
        assert_eq!(parse_line("DO4").unwrap_err().number, 126);
        assert_eq!(parse_line("GOTO 0").unwrap_err().number, 128);
        let w = nc("G01 X#[#1+2] Z-#3 ,C1.");
        assert!(w[3].comma && w[3].letter == 'C');
        assert_eq!(
            parse_line("#1=ATAN[1]/[2]").unwrap().stmt,
            Stmt::Assign {
                var: Expr::Num { v: 1.0, decimal: false },
                value: Expr::Call(Func::Atan, vec![Expr::Num { v: 1.0, decimal: false }, Expr::Num { v: 2.0, decimal: false }]),
            }
        );
    }

    #[test]
    fn errors_have_numbers_and_columns() {
        let e = parse_line("G01 X10 Z").unwrap_err();
        assert_eq!((e.number, e.col), (5, 9));
        assert_eq!(parse_line("G01 123").unwrap_err().number, 4);
        assert_eq!(parse_line("G01 X123456789").unwrap_err().number, 3);
        assert_eq!(parse_line("G01 @").unwrap_err().number, 9);
        assert_eq!(parse_line("G01 X1 GOTO 5").unwrap_err().number, 127);
        assert_eq!(parse_line("#1=[[[[[[1]]]]]]").unwrap_err().number, 118);
        assert_eq!(parse_line("M-3").unwrap_err().number, 6);
        assert_eq!(parse_line(&format!("#1={}1", "-".repeat(100_000))).unwrap_err().number, 114);
        assert_eq!(parse_line(&format!("#1={}1", "#".repeat(100_000))).unwrap_err().number, 114);
    }

    #[test]
    fn sinumerik_cycle_calls() {
        let b = parse_line("N20 mcall cycle81(100, 0,1,,25,0.6,,,) ; centre").unwrap();
        assert_eq!(b.n, Some(20));
        let Stmt::Call { mcall, name, args, cols } = b.stmt else { panic!() };
        assert!(mcall);
        assert_eq!(name.as_deref(), Some("CYCLE81"));
        let num = |v: f64| Some(Expr::Num { v, decimal: v.fract() != 0.0 });
        assert_eq!(args, [num(100.0), num(0.0), num(1.0), None, num(25.0), num(0.6)]);
        assert_eq!(cols, [19, 24, 26, 28, 29, 32]);
        assert_eq!(parse_line("MCALL").unwrap().stmt, Stmt::Call { mcall: true, name: None, args: vec![], cols: vec![] });
        let b = parse_line("CYCLE84(5,0,2,-[3*5],,#1) (tap)").unwrap();
        let Stmt::Call { args, .. } = b.stmt else { panic!() };
        assert_eq!(args.len(), 6);
        assert!(matches!(args[3], Some(Expr::Neg(_))));
        assert!(matches!(args[5], Some(Expr::Var(_))));
        // Errors with their columns.
        assert_eq!(parse_line("CYCLE81(1,2").map_err(|e| (e.number, e.col)).unwrap_err(), (9, 12));
        assert_eq!(parse_line("CYCLE81 X1").map_err(|e| (e.number, e.col)).unwrap_err(), (9, 9));
        assert_eq!(parse_line("CYCLE81(1,2) X5").map_err(|e| (e.number, e.col)).unwrap_err(), (9, 14));
        assert_eq!(parse_line("CYCLE81(1,2 3)").map_err(|e| (e.number, e.col)).unwrap_err(), (9, 13));
        assert_eq!(parse_line("MCALL X1").map_err(|e| e.number).unwrap_err(), 9);
        // Ordinary blocks are not calls.
        assert!(matches!(parse_line("C10 Z5").unwrap().stmt, Stmt::Nc(_)));
    }
}
