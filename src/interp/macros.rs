//! Macro variables and expression evaluation (manual §2.24).
//!
//! Values are `Option<f64>`: `None` is the manual's "null" (空). Null rules (§2.24.1):
//! a bare null variable passes through (`#1=#2` keeps null, `X#2` drops the word); in any
//! arithmetic null counts as 0; in comparisons null differs from 0: with both sides null
//! EQ/GE/LE hold, with one side null only NE holds.
//!
//! Variable ranges (§2.24.1): #0 always null (read-only), #1–#400 and #601–#999 local (one set
//! per macro call level), #401–#600 common. Writing #3000 is the Fanuc user alarm
//! (`Interpreter::assign`); other numbers (Fanuc system variables #1000+) are not available
//! yet: PS0115.
//!
//! Alarm numbers are Fanuc's: 112 division by zero, 111 overflow, 115 variable number out of
//! range, 116 write-protected variable, 119 argument out of range.

use super::parse::{BinOp, Expr, Func};
use std::collections::HashMap;

pub type Value = Option<f64>;

/// A run-time macro error: number and message (the caller adds position and block).
#[derive(Clone, Debug, PartialEq)]
pub struct MErr {
    pub number: u32,
    pub message: String,
}

fn merr<T>(number: u32, message: impl Into<String>) -> Result<T, MErr> {
    Err(MErr { number, message: message.into() })
}

#[derive(Clone, Debug, Default)]
pub struct Vars {
    /// Local variables, one map per macro call level (index 0 = the main program).
    pub locals: Vec<HashMap<u32, f64>>,
    pub common: HashMap<u32, f64>,
}

pub fn is_local(n: u32) -> bool {
    (1..=400).contains(&n) || (601..=999).contains(&n)
}
pub fn is_common(n: u32) -> bool {
    (401..=600).contains(&n)
}

impl Vars {
    pub fn new() -> Self {
        Vars { locals: vec![HashMap::new()], common: HashMap::new() }
    }

    fn number(v: f64) -> Result<u32, MErr> {
        let r = v.round();
        if !(0.0..=99_999_999.0).contains(&r) || (r - v).abs() > 1e-6 {
            return merr(115, format!("#{v}: a variable number must be a whole number 0–999"));
        }
        Ok(r as u32)
    }

    pub fn get(&self, n: u32) -> Result<Value, MErr> {
        if n == 0 {
            Ok(None)
        } else if is_local(n) {
            Ok(self.locals.last().and_then(|m| m.get(&n).copied()))
        } else if is_common(n) {
            Ok(self.common.get(&n).copied())
        } else {
            merr(115, format!("#{n} is not available (variables are #0–#999)"))
        }
    }

    pub fn set(&mut self, n: u32, v: Value) -> Result<(), MErr> {
        if n == 0 {
            return merr(116, "#0 is always null and cannot be written");
        }
        let map = if is_local(n) {
            match self.locals.last_mut() {
                Some(m) => m,
                None => return merr(115, "no local variable level"),
            }
        } else if is_common(n) {
            &mut self.common
        } else {
            return merr(115, format!("#{n} is not available (variables are #0–#999)"));
        };
        match v {
            Some(x) => {
                if !x.is_finite() {
                    return merr(111, format!("#{n}: value overflows"));
                }
                map.insert(n, x);
            }
            None => {
                map.remove(&n);
            }
        }
        Ok(())
    }

    /// The variable number an assignment target `#<e>` designates.
    pub fn target(&self, e: &Expr) -> Result<u32, MErr> {
        let v = self.eval(e)?.unwrap_or(0.0);
        Self::number(v)
    }

    /// Evaluate in a macro statement.
    pub fn eval(&self, e: &Expr) -> Result<Value, MErr> {
        self.eval_in(e, false)
    }

    /// Evaluate an NC word's value: there ROUND rounds at the least input increment (0.001)
    /// instead of to an integer (§2.24.2 (7)).
    pub fn eval_nc(&self, e: &Expr) -> Result<Value, MErr> {
        self.eval_in(e, true)
    }

    fn eval_in(&self, e: &Expr, nc: bool) -> Result<Value, MErr> {
        Ok(match e {
            Expr::Num { v, .. } => Some(*v),
            Expr::Var(inner) => {
                let n = Self::number(self.eval_in(inner, nc)?.unwrap_or(0.0))?;
                self.get(n)?
            }
            Expr::Paren(inner) => self.eval_in(inner, nc)?,
            Expr::Neg(inner) => self.eval_in(inner, nc)?.map(|v| -v),
            Expr::Bin(op, a, b) => {
                let (a, b) = (self.eval_in(a, nc)?, self.eval_in(b, nc)?);
                Some(binop(*op, a, b)?)
            }
            Expr::Call(f, args) => {
                let mut v = Vec::with_capacity(args.len());
                for a in args {
                    v.push(self.eval_in(a, nc)?.unwrap_or(0.0));
                }
                Some(call(*f, &v, nc)?)
            }
        })
    }
}

fn bool_v(b: bool) -> f64 {
    if b {
        1.0
    } else {
        0.0
    }
}

fn int_of(x: f64, what: &str) -> Result<i64, MErr> {
    if x.fract() != 0.0 || x.abs() > 1e15 {
        return merr(119, format!("{what} needs whole numbers, got {x}"));
    }
    Ok(x as i64)
}

fn binop(op: BinOp, a: Value, b: Value) -> Result<f64, MErr> {
    use BinOp::*;
    if let Eq | Ne | Gt | Ge | Lt | Le = op {
        return Ok(bool_v(match (a, b) {
            (None, None) => matches!(op, Eq | Ge | Le),
            (None, _) | (_, None) => op == Ne,
            (Some(x), Some(y)) => match op {
                Eq => x == y,
                Ne => x != y,
                Gt => x > y,
                Ge => x >= y,
                Lt => x < y,
                _ => x <= y,
            },
        }));
    }
    let (x, y) = (a.unwrap_or(0.0), b.unwrap_or(0.0));
    let r = match op {
        Add => x + y,
        Sub => x - y,
        Mul => x * y,
        Div => {
            if y == 0.0 {
                return merr(112, "division by zero");
            }
            x / y
        }
        Mod => {
            let (i, j) = (int_of(x.trunc(), "MOD")?, int_of(y.trunc(), "MOD")?);
            if j == 0 {
                return merr(112, "MOD by zero");
            }
            (i % j) as f64
        }
        And => (int_of(x, "AND")? & int_of(y, "AND")?) as f64,
        Or => (int_of(x, "OR")? | int_of(y, "OR")?) as f64,
        Xor => (int_of(x, "XOR")? ^ int_of(y, "XOR")?) as f64,
        _ => unreachable!("comparisons handled above"),
    };
    if !r.is_finite() {
        return merr(111, "calculated value overflows");
    }
    Ok(r)
}

fn call(f: Func, a: &[f64], nc: bool) -> Result<f64, MErr> {
    let x = a.first().copied().unwrap_or(0.0);
    let r = match f {
        Func::Sin => x.to_radians().sin(),
        Func::Cos => x.to_radians().cos(),
        Func::Tan => {
            // TAN[90], TAN[270] are a division by zero (manual §2.24.2 (6)).
            if (x.rem_euclid(180.0) - 90.0).abs() < 1e-9 {
                return merr(112, format!("TAN[{x}] is infinite"));
            }
            x.to_radians().tan()
        }
        Func::Asin | Func::Acos => {
            if !(-1.0..=1.0).contains(&x) {
                return merr(119, format!("ASIN/ACOS argument {x} is outside −1…1"));
            }
            if f == Func::Asin {
                x.asin().to_degrees()
            } else {
                x.acos().to_degrees()
            }
        }
        Func::Atan => {
            if a.len() == 2 {
                // The manual's example gives ATAN[-1]/[-1] = 45°, i.e. the angle of the ratio
                // j/k (−90…90], not Fanuc's quadrant-correct 225°. We follow the manual.
                let k = a[1];
                if k == 0.0 {
                    if x == 0.0 {
                        return merr(112, "ATAN[0]/[0] is undefined");
                    }
                    90.0f64.copysign(x)
                } else {
                    (x / k).atan().to_degrees()
                }
            } else {
                x.atan().to_degrees()
            }
        }
        Func::Sqrt => {
            if x < 0.0 {
                return merr(119, format!("SQRT of a negative number ({x})"));
            }
            x.sqrt()
        }
        Func::Abs => x.abs(),
        // In a macro statement ROUND rounds at the first decimal (to an integer), half away
        // from zero like Fanuc.
        Func::Round if nc => (x * 1000.0).round() / 1000.0,
        Func::Round => x.round(),
        Func::Fix => x.trunc(),
        Func::Fup => {
            if x >= 0.0 {
                x.ceil()
            } else {
                x.floor()
            }
        }
        Func::Ln => {
            if x <= 0.0 {
                return merr(119, format!("LN of {x} (must be > 0)"));
            }
            x.ln()
        }
        Func::Exp => {
            if !(-80.0..=80.0).contains(&x) {
                return merr(119, format!("EXP[{x}]: the argument must be within −80…80"));
            }
            x.exp()
        }
        Func::Max => x.max(a.get(1).copied().unwrap_or(0.0)),
        Func::Min => x.min(a.get(1).copied().unwrap_or(0.0)),
        Func::Bin => {
            let v = int_of(x, "BIN")?;
            let mut r = 0i64;
            let mut m = 1i64;
            let mut v = v;
            while v > 0 {
                let d = v & 0xF;
                if d > 9 {
                    return merr(119, "BIN: argument is not a BCD value");
                }
                r += d * m;
                m *= 10;
                v >>= 4;
            }
            r as f64
        }
        Func::Bcd => {
            let mut v = int_of(x, "BCD")?;
            if v < 0 {
                return merr(119, "BCD of a negative number");
            }
            let mut r = 0i64;
            let mut s = 0;
            while v > 0 && s < 60 {
                r |= (v % 10) << s;
                v /= 10;
                s += 4;
            }
            r as f64
        }
    };
    if !r.is_finite() {
        return merr(111, "calculated value overflows");
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::interp::parse::{parse_line, Stmt};

    fn ev(vars: &Vars, src: &str) -> Result<Value, MErr> {
        match parse_line(&format!("#1={src}")).unwrap().stmt {
            Stmt::Assign { value, .. } => vars.eval(&value),
            _ => panic!(),
        }
    }

    #[test]
    fn arithmetic_functions_and_null_rules() {
        let mut v = Vars::new();
        v.set(10, Some(0.0)).unwrap();
        assert_eq!(ev(&v, "1+2*3").unwrap(), Some(7.0));
        assert_eq!(ev(&v, "[1+2]*3").unwrap(), Some(9.0));
        assert!((ev(&v, "SIN[30]").unwrap().unwrap() - 0.5).abs() < 1e-12);
        assert!((ev(&v, "ACOS[0]").unwrap().unwrap() - 90.0).abs() < 1e-12);
        assert_eq!(ev(&v, "ATAN[1]/[1]").unwrap(), Some(45.0));
        assert_eq!(ev(&v, "ATAN[-1]/[-1]").unwrap(), Some(45.0));
        assert_eq!(ev(&v, "7MOD3").unwrap(), Some(1.0));
        assert_eq!(ev(&v, "ROUND[1.5]").unwrap(), Some(2.0));
        let Stmt::Assign { value, .. } = parse_line("#1=ROUND[1.23456]").unwrap().stmt else { panic!() };
        assert_eq!(v.eval_nc(&value).unwrap(), Some(1.235));
        assert_eq!(ev(&v, "FIX[-1.5]").unwrap(), Some(-1.0));
        assert_eq!(ev(&v, "FUP[1.2]").unwrap(), Some(2.0));
        assert_eq!(ev(&v, "MAX[2,5]").unwrap(), Some(5.0));
        // Null: a bare null stays null, arithmetic treats it as 0.
        assert_eq!(ev(&v, "#2").unwrap(), None);
        assert_eq!(ev(&v, "#2*3").unwrap(), Some(0.0));
        assert_eq!(ev(&v, "#2+#2").unwrap(), Some(0.0));
        // Conditions: null vs null → EQ GE LE hold; 0 vs null → only NE holds.
        assert_eq!(ev(&v, "[#2 EQ #0]").unwrap(), Some(1.0));
        assert_eq!(ev(&v, "[#2 GE #0]").unwrap(), Some(1.0));
        assert_eq!(ev(&v, "[#2 GT #0]").unwrap(), Some(0.0));
        assert_eq!(ev(&v, "[#10 NE #0]").unwrap(), Some(1.0));
        assert_eq!(ev(&v, "[#10 EQ #0]").unwrap(), Some(0.0));
        assert_eq!(ev(&v, "[#10 LE #0]").unwrap(), Some(0.0));
        assert_eq!(ev(&v, "[1 <> 2]").unwrap(), Some(1.0));
        assert_eq!(ev(&v, "[2 >= 2]").unwrap(), Some(1.0));
    }

    #[test]
    fn errors() {
        let mut v = Vars::new();
        assert_eq!(ev(&v, "1/0").unwrap_err().number, 112);
        assert_eq!(ev(&v, "SQRT[-1]").unwrap_err().number, 119);
        assert_eq!(ev(&v, "ASIN[2]").unwrap_err().number, 119);
        assert_eq!(ev(&v, "TAN[90]").unwrap_err().number, 112);
        assert_eq!(ev(&v, "#1000").unwrap_err().number, 115);
        assert_eq!(v.set(0, Some(1.0)).unwrap_err().number, 116);
        v.set(500, Some(3.0)).unwrap();
        assert_eq!(v.get(500).unwrap(), Some(3.0));
    }
}
