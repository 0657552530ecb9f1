//! The CANopen master: SDO client, start-up configuration, PDO exchange, CiA 402 control.
//! Frame codecs come from `cncgw_bus::canopen` (shared with sim-drives).

pub mod master;
pub mod sdo_client;

pub use master::{CanOpenMaster, NodeInfo, NodeSpec};
