//! A machine whose drives are on several buses (X and Z on CANopen, a tailstock on Modbus):
//! one `DriveBus` over the parts, keeping the configuration's axis order.

use super::{AxisFeedback, DriveBus};
use crate::Alarm;
use cncgw_bus::Clock;

pub struct MultiBus<'a> {
    parts: Vec<&'a mut dyn DriveBus>,
    /// Machine axis → (part, axis within the part).
    map: Vec<(usize, usize)>,
}

impl<'a> MultiBus<'a> {
    /// `order` names the machine's axes in configuration order; each must be an axis of
    /// exactly one part.
    pub fn new(parts: Vec<&'a mut dyn DriveBus>, order: &[String]) -> Result<MultiBus<'a>, Alarm> {
        let mut map = Vec::with_capacity(order.len());
        for name in order {
            let found: Vec<(usize, usize)> =
                parts.iter().enumerate().flat_map(|(p, b)| (0..b.axis_count()).filter(|&i| b.axis_name(i) == name).map(move |i| (p, i))).collect();
            match found.as_slice() {
                [one] => map.push(*one),
                [] => return Err(Alarm::new(crate::alarm::CONFIG, format!("axis {name} is on no bus"))),
                _ => return Err(Alarm::new(crate::alarm::CONFIG, format!("axis {name} is on more than one bus"))),
            }
        }
        Ok(MultiBus { parts, map })
    }
}

impl DriveBus for MultiBus<'_> {
    fn startup(&mut self, clock: &mut dyn Clock) -> Result<(), Alarm> {
        for p in self.parts.iter_mut() {
            p.startup(clock)?;
        }
        Ok(())
    }
    fn receive(&mut self, now_ns: u64) -> Result<(), Alarm> {
        // Every part hears its news even when another fails, so nothing is left queued.
        let mut first = Ok(());
        for p in self.parts.iter_mut() {
            let r = p.receive(now_ns);
            if first.is_ok() {
                first = r;
            }
        }
        first
    }
    fn feedback(&self, axis: usize) -> AxisFeedback {
        let (p, i) = self.map[axis];
        self.parts[p].feedback(i)
    }
    fn set_target(&mut self, axis: usize, pos: f64) {
        let (p, i) = self.map[axis];
        self.parts[p].set_target(i, pos)
    }
    fn target_counts(&self, axis: usize) -> i64 {
        let (p, i) = self.map[axis];
        self.parts[p].target_counts(i)
    }
    fn transmit(&mut self, now_ns: u64) -> Result<(), Alarm> {
        let mut first = Ok(());
        for p in self.parts.iter_mut() {
            let r = p.transmit(now_ns);
            if first.is_ok() {
                first = r;
            }
        }
        first
    }
    fn enable_step(&mut self) -> Result<bool, Alarm> {
        let mut all = true;
        for p in self.parts.iter_mut() {
            all &= p.enable_step()?;
        }
        Ok(all)
    }
    fn quick_stop(&mut self) {
        for p in self.parts.iter_mut() {
            p.quick_stop();
        }
    }
    fn shutdown(&mut self, clock: &mut dyn Clock) {
        for p in self.parts.iter_mut() {
            p.shutdown(clock);
        }
    }
    fn axis_count(&self) -> usize {
        self.map.len()
    }
    fn axis_name(&self, axis: usize) -> &str {
        let (p, i) = self.map[axis];
        self.parts[p].axis_name(i)
    }
    fn counts_per_unit(&self, axis: usize) -> f64 {
        let (p, i) = self.map[axis];
        self.parts[p].counts_per_unit(i)
    }
    fn link_cycle(&self, axis: usize) -> Option<(String, String, f64)> {
        let (p, i) = self.map[axis];
        self.parts[p].link_cycle(i)
    }
    fn isolate_faults(&mut self, on: bool) -> bool {
        // Only when every part can: a part that quick-stops its own drives on a fault would
        // leave a synchronised partner on another bus alone.
        let mut all = true;
        for p in self.parts.iter_mut() {
            all &= p.isolate_faults(on);
        }
        if on && !all {
            for p in self.parts.iter_mut() {
                p.isolate_faults(false);
            }
        }
        all
    }
    fn faulted(&self) -> Option<usize> {
        (0..self.map.len()).find(|&a| {
            let (p, i) = self.map[a];
            self.parts[p].faulted() == Some(i)
        })
    }
    fn abandon_startup(&mut self, clock: &mut dyn Clock) {
        for p in self.parts.iter_mut() {
            p.abandon_startup(clock);
        }
    }
    fn io_inputs(&self, node: u8) -> Option<u32> {
        self.parts.iter().find_map(|p| p.io_inputs(node))
    }
    fn set_io_outputs(&mut self, node: u8, bits: u32) {
        for p in self.parts.iter_mut() {
            p.set_io_outputs(node, bits);
        }
    }
    fn following_window(&self, axis: usize) -> Option<f64> {
        let (p, i) = self.map[axis];
        self.parts[p].following_window(i)
    }
    fn torque_permille(&self, axis: usize) -> Option<i16> {
        let (p, i) = self.map[axis];
        self.parts[p].torque_permille(i)
    }
    fn max_torque_permille(&self, axis: usize) -> Option<u16> {
        let (p, i) = self.map[axis];
        self.parts[p].max_torque_permille(i)
    }
    fn position_lost(&self, axis: usize) -> Option<String> {
        let (p, i) = self.map[axis];
        self.parts[p].position_lost(i)
    }
    fn set_spindle_control(&mut self, axis: usize, control: super::SpindleControl) -> bool {
        let (p, i) = self.map[axis];
        self.parts[p].set_spindle_control(i, control)
    }

    fn holds_position(&self, axis: usize) -> bool {
        let (p, i) = self.map[axis];
        self.parts[p].holds_position(i)
    }
}
