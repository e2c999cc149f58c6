//! The served API only grows. The descriptors a real server hands out through reflection (what any
//! client in any language generates its stubs from) are flattened into one line per element (message,
//! field with its number, type, label and oneof, enum value with its number, method with its types
//! and streaming) and compared with the committed snapshot `proto/api-snapshot.txt`: a line of the
//! snapshot that the server no longer serves is a removed, renamed, renumbered or retyped element, a
//! breaking change for clients of `radserve.v1` (the checks of `buf breaking`'s WIRE_JSON rules that
//! matter to a client). New elements must be recorded in the snapshot too, so that they are held from
//! then on: `RADSERVE_UPDATE_API_SNAPSHOT=1 cargo test --release -p radserve --test api_compat`
//! (`make api-snapshot`) appends them, and refuses while anything was removed.

mod common;

use std::collections::BTreeSet;
use std::path::PathBuf;

use common::{connect, start_fake_server};
use prost::Message;
use prost_types::{field_descriptor_proto, DescriptorProto, EnumDescriptorProto, FileDescriptorProto};
use radserve_core::Limits;
use tokio_stream::StreamExt;
use tonic_reflection::pb::v1::{
    server_reflection_client::ServerReflectionClient, server_reflection_request::MessageRequest,
    server_reflection_response::MessageResponse, ServerReflectionRequest,
};

/// The services whose API is held: radserve's own and the dm_env_rpc protocol it serves.
const SERVICES: &[&str] = &["radserve.v1.RadServe", "dm_env_rpc.v1.Environment"];

fn snapshot_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../proto/api-snapshot.txt")
}

fn enum_lines(scope: &str, descriptor: &EnumDescriptorProto, lines: &mut BTreeSet<String>) {
    let name = format!("{scope}.{}", descriptor.name());
    lines.insert(format!("enum {name}"));
    for value in &descriptor.value {
        lines.insert(format!("enum_value {name}.{} = {}", value.name(), value.number()));
    }
}

fn message_lines(scope: &str, descriptor: &DescriptorProto, lines: &mut BTreeSet<String>) {
    let name = format!("{scope}.{}", descriptor.name());
    lines.insert(format!("message {name}"));
    for field in &descriptor.field {
        let kind = field.r#type().as_str_name().trim_start_matches("TYPE_").to_lowercase();
        let label = match field.label() {
            field_descriptor_proto::Label::Repeated => "repeated",
            field_descriptor_proto::Label::Required => "required",
            field_descriptor_proto::Label::Optional if field.proto3_optional() => "optional",
            field_descriptor_proto::Label::Optional => "singular",
        };
        let type_name = field.type_name.as_deref().map(|type_name| format!(" {type_name}")).unwrap_or_default();
        // A proto3 `optional` is a synthetic oneof: its presence is the label above.
        let oneof = match field.oneof_index {
            Some(index) if !field.proto3_optional() => format!(" oneof {}", descriptor.oneof_decl[index as usize].name()),
            _ => String::new(),
        };
        lines.insert(format!("field {name}.{} = {} {label} {kind}{type_name}{oneof}", field.name(), field.number()));
    }
    for nested in &descriptor.nested_type {
        message_lines(&name, nested, lines);
    }
    for nested in &descriptor.enum_type {
        enum_lines(&name, nested, lines);
    }
}

fn file_lines(file: &FileDescriptorProto, lines: &mut BTreeSet<String>) {
    let scope = file.package();
    for message in &file.message_type {
        message_lines(scope, message, lines);
    }
    for descriptor in &file.enum_type {
        enum_lines(scope, descriptor, lines);
    }
    for service in &file.service {
        let name = format!("{scope}.{}", service.name());
        lines.insert(format!("service {name}"));
        for method in &service.method {
            let stream = |streams: bool| if streams { "stream " } else { "" };
            lines.insert(format!(
                "method {name}.{}({}{}) returns ({}{})",
                method.name(),
                stream(method.client_streaming()),
                method.input_type(),
                stream(method.server_streaming()),
                method.output_type()
            ));
        }
    }
}

/// The API the server serves, one line per element, for the files that declare `SERVICES`.
async fn served_api(address: &str) -> BTreeSet<String> {
    let mut reflection = ServerReflectionClient::new(connect(address).await);
    let requests = SERVICES.iter().map(|service| ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::FileContainingSymbol(service.to_string())),
    });
    let mut replies = reflection.server_reflection_info(tokio_stream::iter(requests.collect::<Vec<_>>())).await.unwrap().into_inner();
    let mut lines = BTreeSet::new();
    for service in SERVICES {
        let reply = replies.next().await.expect("one answer per request").unwrap();
        let Some(MessageResponse::FileDescriptorResponse(files)) = reply.message_response else {
            panic!("reflection has no file declaring {service}: {:?}", reply.message_response)
        };
        let package = service.rsplit_once('.').unwrap().0;
        for bytes in files.file_descriptor_proto {
            let file = FileDescriptorProto::decode(bytes.as_slice()).unwrap();
            if file.package() == package {
                file_lines(&file, &mut lines);
            }
        }
    }
    lines
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_served_api_keeps_every_element_of_the_snapshot() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let served = served_api(&server.address).await;
    assert!(served.iter().any(|line| line.starts_with("method radserve.v1.RadServe.Step(")), "reflection served no Step: {served:?}");

    let path = snapshot_path();
    let text = std::fs::read_to_string(&path).unwrap_or_default();
    let recorded: BTreeSet<String> = text.lines().filter(|line| !line.is_empty() && !line.starts_with('#')).map(String::from).collect();
    let removed: Vec<&String> = recorded.difference(&served).collect();
    let added: Vec<&String> = served.difference(&recorded).collect();
    assert!(
        removed.is_empty(),
        "the served API lost or changed {} element(s) of {}: a breaking change for radserve.v1 clients (add a \
         new field, method or value instead, and leave the old one; a real break is a new package, radserve.v2):\n{}",
        removed.len(),
        path.display(),
        removed.iter().map(|line| format!("  {line}")).collect::<Vec<_>>().join("\n")
    );
    if added.is_empty() {
        return;
    }
    if std::env::var_os("RADSERVE_UPDATE_API_SNAPSHOT").is_some() {
        let header = "# The API radserve serves (radserve.v1 and dm_env_rpc.v1), one line per element: \
                      server/radserve/tests/api_compat.rs\n# fails when a line disappears. Written by `make api-snapshot`.\n";
        let body: String = served.iter().map(|line| format!("{line}\n")).collect();
        std::fs::write(&path, format!("{header}{body}")).unwrap();
        eprintln!("api_compat: recorded {} new element(s) in {}", added.len(), path.display());
        return;
    }
    panic!(
        "the served API has {} element(s) that {} does not record yet: run `make api-snapshot` and commit it:\n{}",
        added.len(),
        path.display(),
        added.iter().map(|line| format!("  {line}")).collect::<Vec<_>>().join("\n")
    );
}

/// The flattening itself: a renumbered field and a method that stopped streaming are different lines.
#[test]
fn a_renumbered_field_or_a_changed_method_is_a_different_line() {
    let set = prost_types::FileDescriptorSet::decode(radserve_service::proto::FILE_DESCRIPTOR_SET).unwrap();
    let file = set.file.iter().find(|file| file.package() == "radserve.v1").unwrap().clone();
    let mut original = BTreeSet::new();
    file_lines(&file, &mut original);

    let mut renumbered = file.clone();
    let step = renumbered.message_type.iter_mut().find(|message| message.name() == "StepRequest").unwrap();
    step.field[0].number = Some(step.field[0].number() + 100);
    let mut lines = BTreeSet::new();
    file_lines(&renumbered, &mut lines);
    assert_eq!(original.difference(&lines).count(), 1, "{:?}", original.difference(&lines).collect::<Vec<_>>());

    let mut unstreamed = file.clone();
    let act = unstreamed.service[0].method.iter_mut().find(|method| method.name() == "Act").unwrap();
    act.server_streaming = Some(false);
    let mut lines = BTreeSet::new();
    file_lines(&unstreamed, &mut lines);
    let removed: Vec<_> = original.difference(&lines).collect();
    assert_eq!(removed.len(), 1);
    assert!(removed[0].starts_with("method radserve.v1.RadServe.Act("), "{removed:?}");
}
