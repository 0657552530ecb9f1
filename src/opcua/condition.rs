//! Alarms as OPC UA conditions (OPC 10000-9): the alarm a run stops on is an
//! `AlarmConditionType` (our subtype `CncAlarmConditionType`, with `AlarmNumber`), active and
//! unacknowledged, retained until the process ends; `ConditionRefresh` (and
//! `ConditionRefresh2`) re-send it to a client that subscribed after it.
//!
//! async-opcua 0.19 has no condition support: the event is ours ([`ConditionEvent`]: every
//! field of BaseEventType, ConditionType, AcknowledgeableConditionType and AlarmConditionType
//! a select clause names, by browse path), and so is the refresh ([`RefreshMethods`], a node
//! manager that owns only the two refresh methods of ConditionType and sits before the core
//! one). The condition is also a node ([`ConditionEvent::insert_node`]): its ConditionId
//! `Machine.Alarm.NNNN`, in `Notification/Messages` (40501-1's folder for a machine's
//! conditions), referenced from the machine by HasCondition, its fields the event's as
//! properties and state variables (one implementation: the node reads what the event says).
//! What is missing: no branches, no shelving, and `Acknowledge`/`Confirm`/`Enable`/
//! `Disable`/`AddComment` are refused (`BadNotSupported`, the core node manager's answer):
//! the server is read-only, acknowledging an alarm happens at the machine.

use opcua::nodes::{BaseEventType, Event};
use opcua::server::address_space::{AccessLevel, AddressSpace, ObjectBuilder, VariableBuilder};
use opcua::server::node_manager::{BrowseNode, BrowsePathItem, MethodCall, NodeManager, ReadNode, RequestContext, ServerContext};
use opcua::server::EventField;
use opcua::types::{
    AttributeId, ByteString, DataTypeId, DateTime, LocalizedText, MethodId, NodeId, NumericRange, ObjectId, ObjectTypeId, QualifiedName,
    ReferenceTypeId, StatusCode, TimestampsToReturn, UAString, VariableTypeId, Variant, VariantScalarTypeId,
};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// One alarm as a condition: what the events say of it.
#[derive(Clone, Debug)]
pub struct AlarmCondition {
    pub number: u32,
    pub text: String,
    /// 1 … 1000 (E-stop 1000, other alarms 800).
    pub severity: u16,
    /// When it became active.
    pub time: DateTime,
    pub active: bool,
    pub acked: bool,
}

/// What the server's conditions share: the type, the notifiers, the retained conditions.
pub struct Conditions {
    pub ns: u16,
    /// `CncAlarmConditionType`.
    pub event_type: NodeId,
    /// The machine object (the conditions' source; events go to it and to Server).
    pub machine: NodeId,
    pub machine_name: String,
    /// The variable the alarm number also shows in (the conditions' InputNode).
    pub input_node: NodeId,
    /// Conditions with Retain: what a refresh re-sends.
    pub retained: Mutex<Vec<AlarmCondition>>,
    events: AtomicU64,
}

impl Conditions {
    pub fn new(ns: u16, machine: NodeId, machine_name: &str) -> Conditions {
        Conditions {
            ns,
            event_type: NodeId::new(ns, "CncAlarmConditionType"),
            machine,
            machine_name: machine_name.to_string(),
            input_node: NodeId::new(ns, "Notification.AlarmNumber"),
            retained: Mutex::new(Vec::new()),
            events: AtomicU64::new(0),
        }
    }

    /// The conditions a refresh re-sends.
    pub fn retained(&self) -> Vec<AlarmCondition> {
        self.retained.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// `c` became active: keep it (retained) and make its event.
    pub fn raise(&self, c: AlarmCondition) -> ConditionEvent {
        let ev = self.event(&c);
        self.retained.lock().unwrap_or_else(|e| e.into_inner()).push(c);
        ev
    }

    /// The event that reports `c` as it stands (a new EventId each time, as Part 9 asks).
    pub fn event(&self, c: &AlarmCondition) -> ConditionEvent {
        let n = self.events.fetch_add(1, Ordering::Relaxed);
        let mut id = [0u8; 16];
        id[..8].copy_from_slice(&n.to_le_bytes());
        id[8..12].copy_from_slice(&c.number.to_le_bytes());
        id[12..].copy_from_slice(&std::process::id().to_le_bytes());
        let mut base = BaseEventType::new(self.event_type.clone(), ByteString::from(id.to_vec()), format!("alarm {}: {}", c.number, c.text), c.time);
        base.receive_time = DateTime::now();
        base.severity = c.severity;
        base.source_node = self.machine.clone();
        base.source_name = UAString::from(self.machine_name.as_str());
        base.condition_class_id = Some(ObjectTypeId::ProcessConditionClassType.into());
        base.condition_class_name = Some(LocalizedText::new("", "ProcessConditionClassType"));
        ConditionEvent {
            base,
            c: c.clone(),
            own: self.event_type.clone(),
            ns: self.ns,
            // (Its fields' nodes: `ConditionEvent::field_id`.)
            condition_id: NodeId::new(self.ns, format!("Machine.Alarm.{}", c.number)),
            input_node: self.input_node.clone(),
        }
    }
}

/// The conditions, once the server knows its namespace index.
pub type Shared = Arc<std::sync::OnceLock<Arc<Conditions>>>;

/// An event of a `CncAlarmConditionType` condition.
#[derive(Debug)]
pub struct ConditionEvent {
    base: BaseEventType,
    c: AlarmCondition,
    own: NodeId,
    ns: u16,
    condition_id: NodeId,
    input_node: NodeId,
}

/// The types whose fields the event has: a select clause may name any of them.
fn is_own_or_super(t: &NodeId, own: &NodeId) -> bool {
    t == own
        || [ObjectTypeId::BaseEventType, ObjectTypeId::ConditionType, ObjectTypeId::AcknowledgeableConditionType, ObjectTypeId::AlarmConditionType]
            .into_iter()
            .any(|s| t == &s)
}

/// A two-state variable's text (`ActiveState`, `AckedState`, `EnabledState`).
fn two_state(on: bool, yes: &str, no: &str) -> Variant {
    LocalizedText::new("en", if on { yes } else { no }).into()
}

impl ConditionEvent {
    /// The ns 0 fields ConditionType and its subtypes add to BaseEventType.
    fn condition_field(&self, path: &[QualifiedName]) -> Option<Variant> {
        let c = &self.c;
        let names: Vec<&str> = path.iter().map(|q| q.name.as_ref()).collect();
        Some(match names.as_slice() {
            ["ConditionName"] => UAString::from(format!("Alarm{}", c.number)).into(),
            ["BranchId"] => NodeId::null().into(),
            // Active or unacknowledged: both, until the process ends.
            ["Retain"] => (c.active || !c.acked).into(),
            ["EnabledState"] => two_state(true, "Enabled", "Disabled"),
            ["EnabledState", "Id"] => true.into(),
            ["Quality"] => StatusCode::Good.into(),
            ["LastSeverity"] => c.severity.into(),
            ["Comment"] => LocalizedText::null().into(),
            ["ClientUserId"] => UAString::null().into(),
            ["Quality" | "LastSeverity" | "Comment", "SourceTimestamp"] => c.time.into(),
            ["AckedState"] => two_state(c.acked, "Acknowledged", "Unacknowledged"),
            ["AckedState", "Id"] => c.acked.into(),
            ["ActiveState"] | ["ActiveState", "EffectiveDisplayName"] => two_state(c.active, "Active", "Inactive"),
            ["ActiveState", "Id"] => c.active.into(),
            ["ActiveState", "TransitionTime"] | ["ActiveState", "EffectiveTransitionTime"] => c.time.into(),
            ["InputNode"] => self.input_node.clone().into(),
            ["SuppressedOrShelved"] => false.into(),
            _ => return None,
        })
    }
}

/// The condition's fields its node shows: (name, variable type, sub-fields). PropertyType
/// ones are properties; state variables (TwoStateVariableType, ConditionVariableType) are
/// components with their own properties. AlarmNumber (our namespace) comes with them.
const NODE_FIELDS: [(&str, VariableTypeId, &[&str]); 22] = [
    ("EventId", VariableTypeId::PropertyType, &[]),
    ("EventType", VariableTypeId::PropertyType, &[]),
    ("SourceNode", VariableTypeId::PropertyType, &[]),
    ("SourceName", VariableTypeId::PropertyType, &[]),
    ("Time", VariableTypeId::PropertyType, &[]),
    ("ReceiveTime", VariableTypeId::PropertyType, &[]),
    ("Message", VariableTypeId::PropertyType, &[]),
    ("Severity", VariableTypeId::PropertyType, &[]),
    ("ConditionClassId", VariableTypeId::PropertyType, &[]),
    ("ConditionClassName", VariableTypeId::PropertyType, &[]),
    ("ConditionName", VariableTypeId::PropertyType, &[]),
    ("BranchId", VariableTypeId::PropertyType, &[]),
    ("Retain", VariableTypeId::PropertyType, &[]),
    ("ClientUserId", VariableTypeId::PropertyType, &[]),
    ("InputNode", VariableTypeId::PropertyType, &[]),
    ("SuppressedOrShelved", VariableTypeId::PropertyType, &[]),
    ("EnabledState", VariableTypeId::TwoStateVariableType, &["Id"]),
    ("ActiveState", VariableTypeId::TwoStateVariableType, &["Id", "TransitionTime"]),
    ("AckedState", VariableTypeId::TwoStateVariableType, &["Id"]),
    ("Quality", VariableTypeId::ConditionVariableType, &["SourceTimestamp"]),
    ("LastSeverity", VariableTypeId::ConditionVariableType, &["SourceTimestamp"]),
    ("Comment", VariableTypeId::ConditionVariableType, &["SourceTimestamp"]),
];

/// A read-only variable of the condition node, typed after its value.
fn condition_variable(a: &mut AddressSpace, id: &NodeId, name: QualifiedName, v: Variant, t: VariableTypeId, parent: &NodeId, property: bool) {
    let dt: NodeId = v.data_type().map_or_else(|| DataTypeId::BaseDataType.into(), |e| e.node_id);
    let display = name.name.to_string();
    let b = VariableBuilder::new(id, name, display)
        .value(v)
        .data_type(dt)
        .access_level(AccessLevel::CURRENT_READ)
        .user_access_level(AccessLevel::CURRENT_READ)
        .has_type_definition(t);
    if property {
        b.property_of(parent.clone()).insert(a);
    } else {
        b.component_of(parent.clone()).insert(a);
    }
}

impl ConditionEvent {
    /// Every field [`NODE_FIELDS`] names (and AlarmNumber), by its node's id: what the node
    /// shows is what this event says.
    pub fn node_values(&self) -> Vec<(NodeId, Variant)> {
        let q = |n: &str| QualifiedName::new(0, n);
        let mut out = Vec::new();
        for (name, _, subs) in NODE_FIELDS {
            out.push((self.field_id(&[name]), self.get_value(AttributeId::Value, &NumericRange::None, &[q(name)])));
            for sub in subs {
                out.push((self.field_id(&[name, sub]), self.get_value(AttributeId::Value, &NumericRange::None, &[q(name), q(sub)])));
            }
        }
        out.push((self.field_id(&["AlarmNumber"]), Variant::UInt32(self.c.number)));
        out
    }

    fn field_id(&self, path: &[&str]) -> NodeId {
        NodeId::new(self.ns, format!("Machine.Alarm.{}.{}", self.c.number, path.join(".")))
    }

    /// Make the condition's node (once per alarm number; later raises only change its values,
    /// see [`Self::node_values`]): a `CncAlarmConditionType` object organized by `folder`,
    /// HasCondition from the machine (its source), its fields as variables.
    pub fn insert_node(&self, a: &mut AddressSpace, folder: &NodeId, machine: &NodeId) {
        let cid = &self.condition_id;
        if a.node_exists(cid) {
            return;
        }
        let name = format!("Alarm{}", self.c.number);
        ObjectBuilder::new(cid, QualifiedName::new(self.ns, name.as_str()), format!("alarm {}: {}", self.c.number, self.c.text))
            .organized_by(folder.clone())
            .has_type_definition(self.own.clone())
            .insert(a);
        a.insert_reference(machine, cid, ReferenceTypeId::HasCondition);
        let values: std::collections::HashMap<NodeId, Variant> = self.node_values().into_iter().collect();
        let value = |id: &NodeId| values.get(id).cloned().unwrap_or(Variant::Empty);
        for (field, t, subs) in NODE_FIELDS {
            let id = self.field_id(&[field]);
            let property = t == VariableTypeId::PropertyType;
            condition_variable(a, &id, QualifiedName::new(0, field), value(&id), t, cid, property);
            for sub in subs {
                let sid = self.field_id(&[field, sub]);
                condition_variable(a, &sid, QualifiedName::new(0, *sub), value(&sid), VariableTypeId::PropertyType, &id, true);
            }
        }
        let id = self.field_id(&["AlarmNumber"]);
        condition_variable(a, &id, QualifiedName::new(self.ns, "AlarmNumber"), value(&id), VariableTypeId::PropertyType, cid, true);
    }
}

impl EventField for ConditionEvent {
    fn get_value(&self, attribute_id: AttributeId, index_range: &NumericRange, remaining_path: &[QualifiedName]) -> Variant {
        if attribute_id != AttributeId::Value || remaining_path.is_empty() {
            return Variant::Empty;
        }
        if let [f] = remaining_path {
            if f.namespace_index == self.ns && f.name.as_ref() == "AlarmNumber" {
                return Variant::UInt32(self.c.number);
            }
        }
        if remaining_path.iter().all(|q| q.namespace_index == 0) {
            if let Some(v) = self.condition_field(remaining_path) {
                return v;
            }
        }
        self.base.get_value(attribute_id, index_range, remaining_path)
    }
}

impl Event for ConditionEvent {
    fn get_field(
        &self,
        type_definition_id: &NodeId,
        attribute_id: AttributeId,
        index_range: &NumericRange,
        browse_path: &[QualifiedName],
    ) -> Variant {
        if !is_own_or_super(type_definition_id, &self.own) {
            return Variant::Empty;
        }
        // The ConditionId: the NodeId attribute of the condition itself (empty path).
        if attribute_id == AttributeId::NodeId && browse_path.is_empty() && type_definition_id != &ObjectTypeId::BaseEventType {
            return self.condition_id.clone().into();
        }
        // (BaseEventType as type: the path alone says which field, OPC 10000-4 7.4.4.5.)
        self.get_value(attribute_id, index_range, browse_path)
    }

    fn time(&self) -> &DateTime {
        self.base.time()
    }

    fn event_type_id(&self) -> &NodeId {
        &self.own
    }
}

/// `ConditionRefresh` / `ConditionRefresh2` of ConditionType: the one thing of a condition a
/// read-only server must do on request. Owns only those two method nodes; reads, browses and
/// path translations of them go to the core node manager (whose nodes they are).
pub struct RefreshMethods {
    /// Set once the server has its namespace (before it listens).
    conditions: Shared,
    context: ServerContext,
}

impl RefreshMethods {
    /// The builder `ServerBuilder::with_node_manager` takes (placed before the core manager).
    pub fn builder(conditions: Shared) -> impl FnOnce(ServerContext) -> RefreshMethods {
        move |context| RefreshMethods { conditions, context }
    }

    fn core(&self) -> Option<Arc<opcua::server::node_manager::DynNodeManager>> {
        self.context.node_managers.iter().find(|m| m.name() == "core")
    }

    /// Check the call, then send, to the subscription's event items, RefreshStart, the
    /// retained conditions and RefreshEnd — one per publishing interval, on a task: an event
    /// item with the default queue (0, revised to 1 by async-opcua) keeps only the last event
    /// of an interval.
    fn refresh(&self, ctx: &RequestContext, call: &mut MethodCall) -> Result<(), StatusCode> {
        let conditions = self.conditions.get().ok_or(StatusCode::BadInternalError)?.clone();
        let two = matches!(call.method_id().as_method_id(), Ok(MethodId::ConditionType_ConditionRefresh2));
        let arg = |k: usize| match call.arguments().get(k).map(|v| v.convert(VariantScalarTypeId::UInt32)) {
            Some(Variant::UInt32(v)) => Ok(v),
            _ => Err(StatusCode::BadInvalidArgument),
        };
        let sub_id = arg(0)?;
        let item = if two { Some(arg(1)?) } else { None };
        let subs = ctx.subscriptions.get_session_subscriptions(ctx.session_id).ok_or(StatusCode::BadSubscriptionIdInvalid)?;
        let (items, interval) = {
            let subs = subs.lock();
            let sub = subs.get(sub_id).ok_or(StatusCode::BadSubscriptionIdInvalid)?;
            let server: NodeId = ObjectId::Server.into();
            let items: Vec<u32> = sub
                .items()
                .filter(|i| i.item_to_monitor().attribute_id == AttributeId::EventNotifier)
                .filter(|i| [&server, &conditions.machine].contains(&&i.item_to_monitor().node_id))
                .map(|i| i.id())
                .filter(|id| item.is_none_or(|x| x == *id))
                .collect();
            (items, sub.publishing_interval())
        };
        if item.is_some() && items.is_empty() {
            return Err(StatusCode::BadMonitoredItemIdInvalid);
        }
        let (cache, session) = (ctx.subscriptions.clone(), ctx.session_id);
        let type_tree = ctx.type_tree.clone();
        let gap = interval + Duration::from_millis(20);
        tokio::spawn(async move {
            let start = BaseEventType::new_now(ObjectTypeId::RefreshStartEventType, ByteString::from(vec![1u8; 16]), "refresh start")
                .set_source_node(ObjectId::Server.into())
                .set_severity(1);
            let end = BaseEventType::new_now(ObjectTypeId::RefreshEndEventType, ByteString::from(vec![2u8; 16]), "refresh end")
                .set_source_node(ObjectId::Server.into())
                .set_severity(1);
            let mut events: Vec<Box<dyn Event + Send + Sync>> = vec![Box::new(start)];
            for c in conditions.retained() {
                events.push(Box::new(conditions.event(&c)));
            }
            events.push(Box::new(end));
            for (k, ev) in events.iter().enumerate() {
                if k > 0 {
                    tokio::time::sleep(gap).await;
                }
                // (The session may have gone meanwhile: then so has the refresh.)
                let Some(subs) = cache.get_session_subscriptions(session) else { return };
                let mut subs = subs.lock();
                let Some(sub) = subs.get_mut(sub_id) else { return };
                let tt = type_tree.read();
                for id in &items {
                    sub.notify_event(id, ev.as_ref(), &*tt);
                }
            }
        });
        call.set_outputs(Vec::new());
        Ok(())
    }
}

#[async_trait::async_trait]
impl NodeManager for RefreshMethods {
    fn owns_node(&self, id: &NodeId) -> bool {
        matches!(id.as_method_id(), Ok(MethodId::ConditionType_ConditionRefresh | MethodId::ConditionType_ConditionRefresh2))
    }

    fn name(&self) -> &str {
        "cncgw-condition-refresh"
    }

    fn namespaces_for_user(&self, _context: &RequestContext) -> Vec<opcua::server::diagnostics::NamespaceMetadata> {
        Vec::new()
    }

    async fn init(&self, _type_tree: &mut opcua::nodes::DefaultTypeTree, _context: ServerContext) {}

    async fn read(&self, context: &RequestContext, max_age: f64, ts: TimestampsToReturn, nodes: &mut [&mut ReadNode]) -> Result<(), StatusCode> {
        self.core().ok_or(StatusCode::BadInternalError)?.read(context, max_age, ts, nodes).await
    }

    async fn browse(&self, context: &RequestContext, nodes: &mut [BrowseNode]) -> Result<(), StatusCode> {
        self.core().ok_or(StatusCode::BadInternalError)?.browse(context, nodes).await
    }

    async fn translate_browse_paths_to_node_ids(&self, context: &RequestContext, nodes: &mut [&mut BrowsePathItem]) -> Result<(), StatusCode> {
        self.core().ok_or(StatusCode::BadInternalError)?.translate_browse_paths_to_node_ids(context, nodes).await
    }

    async fn call(&self, context: &RequestContext, methods: &mut [&mut MethodCall]) -> Result<(), StatusCode> {
        for m in methods {
            match self.refresh(context, m) {
                Ok(()) => m.set_status(StatusCode::Good),
                Err(e) => m.set_status(e),
            }
        }
        Ok(())
    }
}
