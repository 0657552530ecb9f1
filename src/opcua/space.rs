//! The address space: OPC 40501-1 (Machine Tools) where it has a place for the data, our
//! namespace for the rest, and the task's copy of the snapshot into it.
//!
//! ```text
//! Objects/Machines/<machine name>             (events: alarms as CncAlarmConditionType, see `condition`)
//!   Identification    Manufacturer, Model, SoftwareRevision, ProductInstanceUri, ConfigFile
//!   Monitoring
//!     MachineTool     OperationMode, MachineState, MachineStateCode, PowerOnDuration
//!     Channel1        ChannelState, FeedOverride, Feed, SyncError
//!     Spindle1        IsRotating, Override, RotationSpeed, CommandedSpeed, Load (% rated torque)
//!   Production
//!     ActiveProgram   Name, State, Line, BlockCount, Progress, ElapsedTime, EstimatedRemainingTime
//!     ProductionPlan  PartsCompleted
//!   Axes/<X, Z, …>    CommandedPosition, ActualPosition, FollowingError, DriveState, Statusword
//!   Notification      AlarmNumber, AlarmText
//!     Messages        Alarm<NNNN>: the alarm's condition (CncAlarmConditionType; HasCondition
//!                     from the machine), its fields readable (ActiveState/Id, AlarmNumber, …)
//! ```
//!
//! The browse names, folders and enumerations (ChannelState, MachineOperationMode,
//! ProductionProgramState) are 40501-1's; the nodes are typed BaseObjectType /
//! BaseDataVariableType in our namespace, because the companion nodesets (DI, Machinery, IA,
//! MachineTool) are not loaded into the server. Every variable is read-only.

use super::condition::{AlarmCondition, Conditions};
use super::UPDATE_MS;
use crate::control::snapshot::{MachineSnap, MachineState, RunInfo, Snapshot};
use opcua::nodes::Event;
use opcua::server::address_space::{AccessLevel, AddressSpace, EventNotifier, ObjectBuilder, ObjectTypeBuilder, VariableBuilder};
use opcua::server::node_manager::memory::SimpleNodeManager;
use opcua::server::ServerHandle;
use opcua::types::{DataTypeId, DataValue, DateTime, NodeClass, NodeId, ObjectId, ObjectTypeId, QualifiedName, UAString, VariableTypeId, Variant};
use std::sync::Arc;

/// The variables the task writes, by what feeds them.
pub struct Space {
    ns: u16,
    machine: NodeId,
    /// The alarm conditions (`condition`), shared with the refresh methods.
    conditions: Arc<Conditions>,
    /// The last snapshot cycle and alarm written (nothing new: nothing to do).
    last_cycle: u64,
    last_alarm_seq: u64,
    started: std::time::Instant,
}

/// 40501-1 ChannelState: Active 0, Interrupted 1, Reset 2.
fn channel_state(s: MachineState) -> i32 {
    match s {
        MachineState::Running => 0,
        MachineState::Held | MachineState::Alarm | MachineState::EStop => 1,
        MachineState::Idle => 2,
    }
}

/// 40501-1 ProductionProgramState: Initializing 0, Running 1, Ended 2, Interrupted 3, Aborted 4.
fn program_state(s: MachineState, cycle: u64) -> i32 {
    match s {
        MachineState::Running => 1,
        MachineState::Held => 3,
        MachineState::Alarm | MachineState::EStop => 4,
        MachineState::Idle if cycle == 0 => 0,
        MachineState::Idle => 2,
    }
}

/// An object `path` (dotted; its last part the browse name) of `parent`.
fn add_object(a: &mut AddressSpace, ns: u16, path: &str, parent: &NodeId) -> NodeId {
    let name = path.rsplit('.').next().unwrap_or(path);
    let id = NodeId::new(ns, path.to_string());
    ObjectBuilder::new(&id, QualifiedName::new(ns, name), name)
        .component_of(parent.clone())
        .has_type_definition(ObjectTypeId::BaseObjectType)
        .insert(a);
    id
}

/// A read-only variable `path` of `parent`.
fn add_variable(a: &mut AddressSpace, ns: u16, path: &str, parent: &NodeId, v: Variant, t: DataTypeId) {
    let name = path.rsplit('.').next().unwrap_or(path);
    VariableBuilder::new(&NodeId::new(ns, path.to_string()), QualifiedName::new(ns, name), name)
        .value(v)
        .data_type(t)
        .access_level(AccessLevel::CURRENT_READ)
        .user_access_level(AccessLevel::CURRENT_READ)
        .minimum_sampling_interval(UPDATE_MS as f64)
        .component_of(parent.clone())
        .has_type_definition(VariableTypeId::BaseDataVariableType)
        .insert(a);
}

/// A CiA 402 statusword as its state's name.
fn drive_state(sw: u16) -> &'static str {
    use cncgw_bus::cia402::State;
    match State::from_statusword(sw) {
        State::NotReadyToSwitchOn => "NotReadyToSwitchOn",
        State::SwitchOnDisabled => "SwitchOnDisabled",
        State::ReadyToSwitchOn => "ReadyToSwitchOn",
        State::SwitchedOn => "SwitchedOn",
        State::OperationEnabled => "OperationEnabled",
        State::QuickStopActive => "QuickStopActive",
        State::FaultReactionActive => "FaultReactionActive",
        State::Fault => "Fault",
    }
}

impl Space {
    /// Make the nodes (values as before any cycle) and register the alarm event type.
    pub fn build(nm: &SimpleNodeManager, handle: &ServerHandle, ns: u16, machine_name: &str, config_name: &str, axes: &[String]) -> Space {
        let id = |s: &str| NodeId::new(ns, s.to_string());
        let machine = id("Machine");
        let conditions = Arc::new(Conditions::new(ns, machine.clone(), machine_name));
        let event_type = conditions.event_type.clone();
        let alarm_number_prop = id("CncAlarmConditionType.AlarmNumber");
        {
            let mut guard = nm.address_space().write();
            let a = &mut *guard;
            let machines = id("Machines");
            a.add_folder(&machines, QualifiedName::new(ns, "Machines"), "Machines", &ObjectId::ObjectsFolder.into());
            ObjectBuilder::new(&machine, QualifiedName::new(ns, machine_name), machine_name)
                .organized_by(machines)
                .has_type_definition(ObjectTypeId::BaseObjectType)
                .event_notifier(EventNotifier::SUBSCRIBE_TO_EVENTS)
                .insert(a);
            let s = |t: &str| Variant::from(UAString::from(t));
            let ident = add_object(a, ns, "Identification", &machine);
            add_variable(a, ns, "Identification.Manufacturer", &ident, s("cncgw"), DataTypeId::String);
            add_variable(a, ns, "Identification.Model", &ident, s(machine_name), DataTypeId::String);
            add_variable(a, ns, "Identification.SoftwareRevision", &ident, s(env!("CARGO_PKG_VERSION")), DataTypeId::String);
            let uri = super::machine_uri(machine_name);
            add_variable(a, ns, "Identification.ProductInstanceUri", &ident, s(&uri), DataTypeId::String);
            add_variable(a, ns, "Identification.ConfigFile", &ident, s(config_name), DataTypeId::String);
            let mon = add_object(a, ns, "Monitoring", &machine);
            let mt = add_object(a, ns, "Monitoring.MachineTool", &mon);
            add_variable(a, ns, "Monitoring.MachineTool.OperationMode", &mt, Variant::Int32(0), DataTypeId::Int32);
            add_variable(a, ns, "Monitoring.MachineTool.MachineState", &mt, s("Idle"), DataTypeId::String);
            add_variable(a, ns, "Monitoring.MachineTool.MachineStateCode", &mt, Variant::Int32(0), DataTypeId::Int32);
            add_variable(a, ns, "Monitoring.MachineTool.PowerOnDuration", &mt, Variant::Double(0.0), DataTypeId::Double);
            let ch = add_object(a, ns, "Monitoring.Channel1", &mon);
            add_variable(a, ns, "Monitoring.Channel1.ChannelState", &ch, Variant::Int32(2), DataTypeId::Int32);
            for n in ["FeedOverride", "Feed", "SyncError"] {
                add_variable(a, ns, &format!("Monitoring.Channel1.{n}"), &ch, Variant::Double(0.0), DataTypeId::Double);
            }
            let sp = add_object(a, ns, "Monitoring.Spindle1", &mon);
            add_variable(a, ns, "Monitoring.Spindle1.IsRotating", &sp, Variant::Boolean(false), DataTypeId::Boolean);
            for n in ["Override", "RotationSpeed", "CommandedSpeed", "Load"] {
                add_variable(a, ns, &format!("Monitoring.Spindle1.{n}"), &sp, Variant::Double(0.0), DataTypeId::Double);
            }
            let prod = add_object(a, ns, "Production", &machine);
            let prog = add_object(a, ns, "Production.ActiveProgram", &prod);
            add_variable(a, ns, "Production.ActiveProgram.Name", &prog, s(""), DataTypeId::String);
            add_variable(a, ns, "Production.ActiveProgram.State", &prog, Variant::Int32(0), DataTypeId::Int32);
            add_variable(a, ns, "Production.ActiveProgram.Line", &prog, Variant::UInt32(0), DataTypeId::UInt32);
            add_variable(a, ns, "Production.ActiveProgram.BlockCount", &prog, Variant::UInt64(0), DataTypeId::UInt64);
            for n in ["Progress", "ElapsedTime", "EstimatedRemainingTime"] {
                add_variable(a, ns, &format!("Production.ActiveProgram.{n}"), &prog, Variant::Double(0.0), DataTypeId::Double);
            }
            let plan = add_object(a, ns, "Production.ProductionPlan", &prod);
            add_variable(a, ns, "Production.ProductionPlan.PartsCompleted", &plan, Variant::UInt64(0), DataTypeId::UInt64);
            let axes_obj = add_object(a, ns, "Axes", &machine);
            for name in axes {
                let ax = add_object(a, ns, &format!("Axes.{}", name.to_uppercase()), &axes_obj);
                let p = format!("Axes.{}", name.to_uppercase());
                for n in ["CommandedPosition", "ActualPosition", "FollowingError"] {
                    add_variable(a, ns, &format!("{p}.{n}"), &ax, Variant::Double(0.0), DataTypeId::Double);
                }
                add_variable(a, ns, &format!("{p}.DriveState"), &ax, s(""), DataTypeId::String);
                add_variable(a, ns, &format!("{p}.Statusword"), &ax, Variant::UInt16(0), DataTypeId::UInt16);
            }
            let note = add_object(a, ns, "Notification", &machine);
            add_variable(a, ns, "Notification.AlarmNumber", &note, Variant::UInt32(0), DataTypeId::UInt32);
            add_variable(a, ns, "Notification.AlarmText", &note, s(""), DataTypeId::String);
            // 40501-1's folder of the machine's conditions: each alarm's condition node.
            a.add_folder(&id("Notification.Messages"), QualifiedName::new(ns, "Messages"), "Messages", &note);
            // The alarm condition type: AlarmConditionType with the alarm's number.
            ObjectTypeBuilder::new(&event_type, QualifiedName::new(ns, "CncAlarmConditionType"), "CncAlarmConditionType")
                .subtype_of(ObjectTypeId::AlarmConditionType)
                .is_abstract(false)
                .insert(a);
            VariableBuilder::new(&alarm_number_prop, QualifiedName::new(ns, "AlarmNumber"), "AlarmNumber")
                .value(0u32)
                .data_type(DataTypeId::UInt32)
                .access_level(AccessLevel::CURRENT_READ)
                .user_access_level(AccessLevel::CURRENT_READ)
                .property_of(event_type.clone())
                .has_type_definition(VariableTypeId::PropertyType)
                .has_modelling_rule(ObjectId::ModellingRule_Mandatory)
                .insert(a);
        }
        {
            // Event filters resolve types and their fields through the type tree.
            let mut tt = handle.type_tree().write();
            tt.add_type_node(&event_type, &ObjectTypeId::AlarmConditionType.into(), NodeClass::ObjectType);
            tt.add_type_property(&alarm_number_prop, &event_type, &[&QualifiedName::new(ns, "AlarmNumber")], NodeClass::Variable);
            // A select clause for the ConditionId (ConditionType, NodeId attribute, no path:
            // what asyncua and others add to a condition filter) must validate, or async-opcua
            // drops it and the event's fields no longer line up with the client's clauses.
            tt.add_type_property(&id("ConditionType.ConditionId"), &ObjectTypeId::ConditionType.into(), &[], NodeClass::Object);
        }
        Space { ns, machine, conditions, last_cycle: u64::MAX, last_alarm_seq: 0, started: std::time::Instant::now() }
    }

    /// The alarm conditions (the refresh methods read them).
    pub fn conditions(&self) -> Arc<Conditions> {
        self.conditions.clone()
    }

    /// Copy the snapshot into the variables (when it changed) and send a new alarm as an event.
    pub fn update(&mut self, nm: &SimpleNodeManager, handle: &ServerHandle, snapshot: &Snapshot) {
        let snap = snapshot.read();
        let info = snapshot.info();
        if snap.cycle != self.last_cycle || info.alarm_seq != self.last_alarm_seq {
            self.last_cycle = snap.cycle;
            let values = self.values(&snap, &info);
            let ids: Vec<(NodeId, Variant)> = values.into_iter().map(|(p, v)| (NodeId::new(self.ns, p), v)).collect();
            let now = DateTime::now();
            let r = nm.set_values(
                handle.subscriptions(),
                ids.iter()
                    .map(|(id, v)| (id, None, DataValue { value: Some(v.clone()), status: None, source_timestamp: Some(now), ..Default::default() })),
            );
            if let Err(e) = r {
                tracing::warn!("opcua: cannot update the variables: {e}");
            }
        } else {
            let up = self.started.elapsed().as_secs_f64();
            let id = NodeId::new(self.ns, "Monitoring.MachineTool.PowerOnDuration".to_string());
            let _ = nm.set_values(handle.subscriptions(), std::iter::once((&id, None, DataValue::new_now(up))));
        }
        if info.alarm_seq != self.last_alarm_seq {
            self.last_alarm_seq = info.alarm_seq;
            self.alarm_event(nm, handle, &info);
        }
    }

    /// Every variable's value from one snapshot, by node path.
    fn values(&self, s: &MachineSnap, info: &RunInfo) -> Vec<(String, Variant)> {
        let str_ = |t: &str| Variant::from(UAString::from(t));
        let progress = if info.lines > 0 { (s.line as f64 / info.lines as f64 * 100.0).clamp(0.0, 100.0) } else { 0.0 };
        let progress = if s.state == MachineState::Idle && s.parts > 0 && s.alarm == 0 { 100.0 } else { progress };
        let remaining = if progress > 1.0 { s.elapsed_s * (100.0 - progress) / progress } else { 0.0 };
        let running = matches!(s.state, MachineState::Running | MachineState::Held);
        let mut v: Vec<(String, Variant)> = vec![
            // 40501-1 MachineOperationMode: Other 0, Maintenance 1, Setup 2, Processing 3.
            ("Monitoring.MachineTool.OperationMode".into(), Variant::Int32(if running { 3 } else { 0 })),
            ("Monitoring.MachineTool.MachineState".into(), str_(s.state.name())),
            ("Monitoring.MachineTool.MachineStateCode".into(), Variant::Int32(s.state as i32)),
            ("Monitoring.MachineTool.PowerOnDuration".into(), Variant::Double(self.started.elapsed().as_secs_f64())),
            ("Monitoring.Channel1.ChannelState".into(), Variant::Int32(channel_state(s.state))),
            ("Monitoring.Channel1.FeedOverride".into(), Variant::Double(s.feed_override * 100.0)),
            ("Monitoring.Channel1.Feed".into(), Variant::Double(s.feed)),
            ("Monitoring.Channel1.SyncError".into(), Variant::Double(s.sync_err_um)),
            ("Monitoring.Spindle1.IsRotating".into(), Variant::Boolean(s.spindle_act_rpm.abs() > 0.5)),
            ("Monitoring.Spindle1.Override".into(), Variant::Double(s.spindle_override * 100.0)),
            ("Monitoring.Spindle1.RotationSpeed".into(), Variant::Double(s.spindle_act_rpm)),
            ("Monitoring.Spindle1.CommandedSpeed".into(), Variant::Double(s.spindle_cmd_rpm)),
            ("Monitoring.Spindle1.Load".into(), Variant::Double(s.spindle_load_pct)),
            ("Production.ActiveProgram.Name".into(), str_(&info.program)),
            ("Production.ActiveProgram.State".into(), Variant::Int32(program_state(s.state, s.cycle))),
            ("Production.ActiveProgram.Line".into(), Variant::UInt32(s.line)),
            ("Production.ActiveProgram.BlockCount".into(), Variant::UInt64(s.blocks)),
            ("Production.ActiveProgram.Progress".into(), Variant::Double(progress)),
            ("Production.ActiveProgram.ElapsedTime".into(), Variant::Double(s.elapsed_s)),
            ("Production.ActiveProgram.EstimatedRemainingTime".into(), Variant::Double(remaining)),
            ("Production.ProductionPlan.PartsCompleted".into(), Variant::UInt64(s.parts)),
            ("Notification.AlarmNumber".into(), Variant::UInt32(if s.alarm != 0 { s.alarm } else { info.alarm_number })),
            ("Notification.AlarmText".into(), str_(if info.alarm_number != 0 { &info.alarm_text } else { "" })),
        ];
        for (k, name) in info.axes.iter().enumerate().take(s.n_axes as usize) {
            let a = &s.axes[k];
            let p = format!("Axes.{}", name.to_uppercase());
            v.push((format!("{p}.CommandedPosition"), Variant::Double(a.cmd)));
            v.push((format!("{p}.ActualPosition"), Variant::Double(a.act)));
            v.push((format!("{p}.FollowingError"), Variant::Double(a.ferr)));
            v.push((format!("{p}.DriveState"), str_(drive_state(a.statusword))));
            v.push((format!("{p}.Statusword"), Variant::UInt16(a.statusword)));
        }
        v
    }

    /// The alarm as a condition (`condition`), reported as an event of the machine and of
    /// the Server object (where generic clients subscribe): number, text, severity.
    /// The condition is also a node under Notification/Messages, made before the event goes
    /// out (a client that gets the event can browse to its ConditionId).
    fn alarm_event(&self, nm: &SimpleNodeManager, handle: &ServerHandle, info: &RunInfo) {
        let severity = if info.alarm_number == crate::alarm::ESTOP { 1000 } else { 800 };
        let c =
            AlarmCondition { number: info.alarm_number, text: info.alarm_text.clone(), severity, time: DateTime::now(), active: true, acked: false };
        let ev = self.conditions.raise(c);
        ev.insert_node(&mut nm.address_space().write(), &NodeId::new(self.ns, "Notification.Messages".to_string()), &self.machine);
        let values = ev.node_values();
        let now = DateTime::now();
        let r = nm.set_values(
            handle.subscriptions(),
            values
                .iter()
                .map(|(id, v)| (id, None, DataValue { value: Some(v.clone()), status: None, source_timestamp: Some(now), ..Default::default() })),
        );
        if let Err(e) = r {
            tracing::warn!("opcua: cannot update the condition's node: {e}");
        }
        let server: NodeId = ObjectId::Server.into();
        handle.subscriptions().notify_events([(&ev as &dyn Event, &server), (&ev as &dyn Event, &self.machine)].into_iter());
        tracing::info!(number = info.alarm_number, "opcua: alarm event sent");
    }
}
