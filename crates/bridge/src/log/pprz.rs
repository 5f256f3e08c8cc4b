//! Paparazzi traffic in the log: each message's Ivy text on `/pprz/<sender>/<NAME>` and its
//! decoded fields on `/pprz/<sender>/<NAME>/decoded`, one channel pair per sender and
//! message, added on first use.

use std::collections::BTreeMap;

use mcap::records::MessageHeader;
use prost::Message as _;

use super::encode::schema_data;
use super::mcap_out::McapOut;
use super::proto::{self, PprzDecoded, PprzText};
use crate::paparazzi::codec::split_header;
use crate::paparazzi::messages::MessageSet;
use crate::zenoh_net::keyexpr::is_valid_chunk;

struct Pair {
    text: u16,
    decoded: u16,
    seq: u32,
}

/// The `/pprz/…` channels of one log.
pub(super) struct PprzChannels {
    messages: MessageSet,
    schemas: Option<(u16, u16)>,
    pairs: BTreeMap<(String, String), Pair>,
    /// Messages written (text and decoded count once each).
    pub written: u64,
    /// Texts that did not decode (their text is still logged).
    pub undecodable: u64,
}

impl PprzChannels {
    pub(super) fn new() -> Self {
        Self::with_messages(crate::paparazzi::convert::project_messages())
    }

    /// Channels that decode with `messages` (a real flight's own definitions).
    pub(super) fn with_messages(messages: MessageSet) -> Self {
        Self { messages, schemas: None, pairs: BTreeMap::new(), written: 0, undecodable: 0 }
    }

    /// Logs `text` if `key` is a Paparazzi key (`…/pprz/<sender>/<NAME>`); other keys are
    /// ignored.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn write(
        &mut self,
        out: &mut McapOut,
        tick: u64,
        log_time: u64,
        publish_time: u64,
        key: &str,
        direction: &str,
        text: &str,
    ) -> std::io::Result<()> {
        if !key.contains("/pprz/") {
            return Ok(());
        }
        let Some((sender, name, _)) = split_header(text) else { return Ok(()) };
        if !is_valid_chunk(sender) || !is_valid_chunk(name) {
            return Ok(());
        }
        let (text_schema, decoded_schema) = match self.schemas {
            Some(s) => s,
            None => {
                let mut add = |n: &str| out.add_schema(n, "protobuf", &schema_data(n).unwrap_or_default());
                let s = (add("twinswarm.PprzText")?, add("twinswarm.PprzDecoded")?);
                self.schemas = Some(s);
                s
            }
        };
        let id = (sender.to_owned(), name.to_owned());
        if !self.pairs.contains_key(&id) {
            let topic = format!("/pprz/{sender}/{name}");
            let text_ch = out.add_channel(text_schema, &topic, "protobuf", &BTreeMap::new())?;
            let decoded_ch =
                out.add_channel(decoded_schema, &format!("{topic}/decoded"), "protobuf", &BTreeMap::new())?;
            self.pairs.insert(id.clone(), Pair { text: text_ch, decoded: decoded_ch, seq: 0 });
        }
        let pair = self.pairs.get_mut(&id).expect("inserted above");
        let seq = pair.seq;
        pair.seq = seq.wrapping_add(1);
        let header = |channel_id| MessageHeader { channel_id, sequence: seq, log_time, publish_time };
        let body = PprzText { tick, direction: direction.into(), key: key.into(), text: text.into() };
        out.write_to_known_channel(&header(pair.text), &body.encode_to_vec())?;
        match self.messages.decode(text) {
            Ok(msg) => {
                let fields = msg.def.fields.iter().zip(msg.values.iter()).map(|(f, v)| {
                    let v = serde_json::to_value(v).unwrap_or(serde_json::Value::Null);
                    (f.name.clone(), proto::json_to_value(&v))
                });
                let decoded = PprzDecoded {
                    tick,
                    direction: direction.into(),
                    sender: sender.into(),
                    name: name.into(),
                    class: msg.def.class_name.clone(),
                    fields: Some(prost_types::Struct { fields: fields.collect() }),
                };
                out.write_to_known_channel(&header(pair.decoded), &decoded.encode_to_vec())?;
            }
            Err(_) => self.undecodable += 1,
        }
        self.written += 1;
        Ok(())
    }
}
