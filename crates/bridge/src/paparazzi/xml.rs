//! A small element tree over `quick-xml`, with byte offsets kept for every
//! element and attribute so that every error can name the file, the line
//! and the column.
//!
//! The XML files the bridge reads (Paparazzi `messages.xml`, `conf.xml`,
//! telemetry files, our pairing file) are a few hundred kilobytes at most,
//! so they are read whole into a small element tree and then interpreted by
//! the format-specific modules. Comments, processing instructions, the XML
//! declaration and the `DOCTYPE` are skipped; DTDs are not fetched.
//!
//! All errors are [`XmlError`]s. Every variant except [`XmlError::Io`]
//! carries a [`Location`] (`file:line:column`, 1-based, column counted in
//! characters).

use std::fmt;
use std::path::Path;

use quick_xml::events::{BytesStart, Event};
use quick_xml::reader::Reader;
use serde::Serialize;

/// A position in a source file, 1-based.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Location {
    /// The file label given to the parser (usually its path).
    pub file: String,
    /// Line, starting at 1.
    pub line: u32,
    /// Column in characters, starting at 1.
    pub column: u32,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}:{}", self.file, self.line, self.column)
    }
}

/// Errors from reading and interpreting any of the XML files.
///
/// Locations are boxed to keep `Result<_, XmlError>` small.
#[derive(Debug, thiserror::Error)]
pub enum XmlError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// Path that failed.
        path: String,
        /// Underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The text is not well-formed XML.
    #[error("{at}: XML syntax error: {message}")]
    Syntax {
        /// Where the parser stopped.
        at: Box<Location>,
        /// What the XML parser reported.
        message: String,
    },
    /// The root element is not the one this format expects.
    #[error("{at}: expected root element <{expected}>, found <{found}>")]
    WrongRoot {
        /// Position of the root element.
        at: Box<Location>,
        /// Expected root element name.
        expected: String,
        /// Found root element name.
        found: String,
    },
    /// An element that this format does not allow at this place.
    #[error("{at}: unexpected element <{found}> inside <{parent}>")]
    UnexpectedElement {
        /// Position of the element.
        at: Box<Location>,
        /// Name of the enclosing element.
        parent: String,
        /// Name of the offending element.
        found: String,
    },
    /// A required attribute is absent.
    #[error("{at}: <{element}> lacks the required attribute `{attribute}`")]
    MissingAttribute {
        /// Position of the element.
        at: Box<Location>,
        /// Element name.
        element: String,
        /// Name of the missing attribute.
        attribute: String,
    },
    /// An attribute this format does not know (only for our own formats).
    #[error("{at}: unknown attribute `{attribute}` on <{element}>")]
    UnknownAttribute {
        /// Position of the attribute.
        at: Box<Location>,
        /// Element name.
        element: String,
        /// Attribute name.
        attribute: String,
    },
    /// An attribute whose value cannot be interpreted.
    #[error("{at}: <{element} {attribute}=\"{value}\">: {reason}")]
    BadAttribute {
        /// Position of the attribute.
        at: Box<Location>,
        /// Element name.
        element: String,
        /// Attribute name.
        attribute: String,
        /// The raw value.
        value: String,
        /// Why it was rejected.
        reason: String,
    },
    /// Two definitions share a name or id that must be unique.
    #[error("{at}: duplicate {what} `{name}` (first defined at line {first_line})")]
    Duplicate {
        /// Position of the second definition.
        at: Box<Location>,
        /// What kind of thing is duplicated (e.g. "message id").
        what: &'static str,
        /// The duplicated name or id.
        name: String,
        /// Line of the first definition.
        first_line: u32,
    },
    /// Any other semantic error, with its position.
    #[error("{at}: {message}")]
    Invalid {
        /// Position.
        at: Box<Location>,
        /// Description.
        message: String,
    },
}

impl XmlError {
    /// The position the error refers to, if any.
    pub fn location(&self) -> Option<&Location> {
        match self {
            XmlError::Io { .. } => None,
            XmlError::Syntax { at, .. }
            | XmlError::WrongRoot { at, .. }
            | XmlError::UnexpectedElement { at, .. }
            | XmlError::MissingAttribute { at, .. }
            | XmlError::UnknownAttribute { at, .. }
            | XmlError::BadAttribute { at, .. }
            | XmlError::Duplicate { at, .. }
            | XmlError::Invalid { at, .. } => Some(at),
        }
    }

    /// The 1-based line the error refers to, if any.
    pub fn line(&self) -> Option<u32> {
        self.location().map(|l| l.line)
    }
}

/// Reads a whole file to a string, mapping the error to [`XmlError::Io`].
pub fn read_file(path: &Path) -> Result<String, XmlError> {
    std::fs::read_to_string(path).map_err(|source| XmlError::Io { path: path.display().to_string(), source })
}

/// One attribute with the byte offset of its name.
#[derive(Debug, Clone)]
pub(crate) struct Attr {
    pub name: String,
    pub value: String,
    pub offset: usize,
}

/// One element: name, attributes, child elements and its direct text.
#[derive(Debug, Clone)]
pub(crate) struct Element {
    pub name: String,
    /// Byte offset of the `<`.
    pub offset: usize,
    pub attrs: Vec<Attr>,
    pub children: Vec<Element>,
    /// Concatenated direct text and CDATA content (entities resolved).
    pub text: String,
}

/// A parsed document: the root element and what is needed to turn byte
/// offsets into [`Location`]s.
#[derive(Debug)]
pub(crate) struct Doc {
    file: String,
    line_starts: Vec<usize>,
    src: String,
    pub root: Element,
}

impl Doc {
    /// Parses `src`; `file` is the label used in error locations.
    pub fn parse(src: &str, file: &str) -> Result<Doc, XmlError> {
        let line_starts = line_starts(src);
        let mut doc = Doc {
            file: file.to_owned(),
            line_starts,
            src: src.to_owned(),
            root: Element {
                name: String::new(),
                offset: 0,
                attrs: Vec::new(),
                children: Vec::new(),
                text: String::new(),
            },
        };
        doc.root = doc.build_tree()?;
        Ok(doc)
    }

    /// Converts a byte offset into a location.
    pub fn loc(&self, offset: usize) -> Box<Location> {
        let offset = offset.min(self.src.len());
        let line_idx = match self.line_starts.binary_search(&offset) {
            Ok(i) => i,
            Err(i) => i.saturating_sub(1),
        };
        let line_start = self.line_starts.get(line_idx).copied().unwrap_or(0);
        let column = self.src.get(line_start..offset).map(|s| s.chars().count()).unwrap_or(0);
        Box::new(Location {
            file: self.file.clone(),
            line: u32::try_from(line_idx + 1).unwrap_or(u32::MAX),
            column: u32::try_from(column + 1).unwrap_or(u32::MAX),
        })
    }

    /// 1-based line of a byte offset.
    pub fn line(&self, offset: usize) -> u32 {
        self.loc(offset).line
    }

    fn syntax(&self, offset: usize, message: impl Into<String>) -> XmlError {
        XmlError::Syntax { at: self.loc(offset), message: message.into() }
    }

    fn build_tree(&self) -> Result<Element, XmlError> {
        let src = self.src.as_str();
        let mut reader = Reader::from_str(src);
        let config = reader.config_mut();
        config.trim_text(false);
        config.check_end_names = true;
        config.expand_empty_elements = false;

        let mut stack: Vec<Element> = Vec::new();
        let mut root: Option<Element> = None;
        loop {
            let start_pos = usize::try_from(reader.buffer_position()).unwrap_or(usize::MAX);
            let event = match reader.read_event() {
                Ok(ev) => ev,
                Err(e) => {
                    let pos = usize::try_from(reader.error_position()).unwrap_or(usize::MAX);
                    return Err(self.syntax(pos, e.to_string()));
                }
            };
            match event {
                Event::Start(start) => {
                    let el = self.element_from_start(&start, start_pos)?;
                    if root.is_some() && stack.is_empty() {
                        return Err(self.syntax(start_pos, "more than one root element"));
                    }
                    stack.push(el);
                }
                Event::Empty(start) => {
                    let el = self.element_from_start(&start, start_pos)?;
                    match stack.last_mut() {
                        Some(parent) => parent.children.push(el),
                        None if root.is_none() => root = Some(el),
                        None => {
                            return Err(self.syntax(start_pos, "more than one root element"));
                        }
                    }
                }
                Event::End(_) => {
                    let Some(done) = stack.pop() else {
                        return Err(self.syntax(start_pos, "closing tag without opening tag"));
                    };
                    match stack.last_mut() {
                        Some(parent) => parent.children.push(done),
                        None => root = Some(done),
                    }
                }
                Event::Text(t) => {
                    if let Some(cur) = stack.last_mut() {
                        cur.text.push_str(&t.xml10_content());
                    } else if !t.xml10_content().trim().is_empty() {
                        return Err(self.syntax(start_pos, "text outside the root element"));
                    }
                }
                Event::CData(t) => {
                    if let Some(cur) = stack.last_mut() {
                        cur.text.push_str(&t.xml10_content());
                    }
                }
                Event::GeneralRef(r) => {
                    let resolved = match r.resolve_char_ref() {
                        Ok(Some(c)) => c.to_string(),
                        Ok(None) => match &*r.xml10_content() {
                            "lt" => "<".to_owned(),
                            "gt" => ">".to_owned(),
                            "amp" => "&".to_owned(),
                            "apos" => "'".to_owned(),
                            "quot" => "\"".to_owned(),
                            other => {
                                return Err(self.syntax(start_pos, format!("unknown entity `&{other};`")));
                            }
                        },
                        Err(e) => return Err(self.syntax(start_pos, e.to_string())),
                    };
                    if let Some(cur) = stack.last_mut() {
                        cur.text.push_str(&resolved);
                    }
                }
                Event::Comment(_) | Event::Decl(_) | Event::PI(_) | Event::DocType(_) => {}
                Event::Eof => break,
            }
        }
        if let Some(open) = stack.last() {
            return Err(self.syntax(open.offset, format!("element <{}> is never closed", open.name)));
        }
        root.ok_or_else(|| self.syntax(src.len(), "document has no root element"))
    }

    fn element_from_start(&self, start: &BytesStart<'_>, offset: usize) -> Result<Element, XmlError> {
        let name = start.name().as_ref().to_owned();
        let raw_end = (offset + 1 + name.len() + start.attributes_raw().len() + 2).min(self.src.len());
        let raw = self.src.get(offset..raw_end).unwrap_or("");
        let mut attrs = Vec::new();
        for attr in start.attributes() {
            let attr = attr.map_err(|e| self.syntax(offset, e.to_string()))?;
            let key = attr.key.as_ref().to_owned();
            let attr_offset = offset + find_attr_offset(raw, &key).unwrap_or(0);
            let value = attr
                .normalized_value(quick_xml::XmlVersion::Implicit1_0)
                .map_err(|e| self.syntax(attr_offset, e.to_string()))?
                .into_owned();
            attrs.push(Attr { name: key, value, offset: attr_offset });
        }
        Ok(Element { name, offset, attrs, children: Vec::new(), text: String::new() })
    }

    // ---- helpers used by the format modules ----

    /// The value of attribute `name`, if present. Names match without regard to ASCII case,
    /// as in Paparazzi's own reader: `server` writes the definitions it logs with upper-case
    /// attribute names (`NAME`, `TYPE`, `ALT_UNIT_COEF`).
    pub fn attr<'e>(&self, el: &'e Element, name: &str) -> Option<&'e Attr> {
        el.attrs.iter().find(|a| a.name.eq_ignore_ascii_case(name))
    }

    /// The value of a required attribute.
    pub fn req_attr<'e>(&self, el: &'e Element, name: &str) -> Result<&'e Attr, XmlError> {
        self.attr(el, name).ok_or_else(|| XmlError::MissingAttribute {
            at: self.loc(el.offset),
            element: el.name.clone(),
            attribute: name.to_owned(),
        })
    }

    /// Builds a [`XmlError::BadAttribute`] for `attr` of `el`.
    pub fn bad_attr(&self, el: &Element, attr: &Attr, reason: impl Into<String>) -> XmlError {
        XmlError::BadAttribute {
            at: self.loc(attr.offset),
            element: el.name.clone(),
            attribute: attr.name.clone(),
            value: attr.value.clone(),
            reason: reason.into(),
        }
    }

    /// Parses an attribute with `FromStr`, reporting `what` on failure.
    pub fn parse_attr<T: std::str::FromStr>(&self, el: &Element, attr: &Attr, what: &str) -> Result<T, XmlError> {
        attr.value.trim().parse::<T>().map_err(|_| self.bad_attr(el, attr, format!("expected {what}")))
    }

    /// Parses a finite floating-point attribute.
    pub fn parse_f64_attr(&self, el: &Element, attr: &Attr) -> Result<f64, XmlError> {
        let v: f64 = self.parse_attr(el, attr, "a number")?;
        if v.is_finite() { Ok(v) } else { Err(self.bad_attr(el, attr, "expected a finite number")) }
    }

    /// Rejects attributes not in `allowed` (for our own strict formats).
    pub fn only_attrs(&self, el: &Element, allowed: &[&str]) -> Result<(), XmlError> {
        for a in &el.attrs {
            if !allowed.contains(&a.name.as_str()) {
                return Err(XmlError::UnknownAttribute {
                    at: self.loc(a.offset),
                    element: el.name.clone(),
                    attribute: a.name.clone(),
                });
            }
        }
        Ok(())
    }

    /// Error for an element not allowed inside `parent`.
    pub fn unexpected(&self, parent: &Element, child: &Element) -> XmlError {
        XmlError::UnexpectedElement {
            at: self.loc(child.offset),
            parent: parent.name.clone(),
            found: child.name.clone(),
        }
    }

    /// Checks the root element name.
    pub fn expect_root(&self, expected: &str) -> Result<&Element, XmlError> {
        if self.root.name == expected {
            Ok(&self.root)
        } else {
            Err(XmlError::WrongRoot {
                at: self.loc(self.root.offset),
                expected: expected.to_owned(),
                found: self.root.name.clone(),
            })
        }
    }

    /// Builds an [`XmlError::Invalid`] at `offset`.
    pub fn invalid(&self, offset: usize, message: impl Into<String>) -> XmlError {
        XmlError::Invalid { at: self.loc(offset), message: message.into() }
    }
}

/// Byte offsets at which each line starts.
fn line_starts(src: &str) -> Vec<usize> {
    let mut v = vec![0];
    v.extend(src.bytes().enumerate().filter(|(_, b)| *b == b'\n').map(|(i, _)| i + 1));
    v
}

/// Finds `key` followed by optional whitespace and `=` inside the raw text
/// of a start tag, preceded by whitespace. Returns its byte offset.
fn find_attr_offset(raw: &str, key: &str) -> Option<usize> {
    let bytes = raw.as_bytes();
    let mut from = 0;
    while let Some(rel) = raw.get(from..)?.find(key) {
        let pos = from + rel;
        let before_ok = pos > 0 && bytes[pos - 1].is_ascii_whitespace();
        let mut after = pos + key.len();
        while after < bytes.len() && bytes[after].is_ascii_whitespace() {
            after += 1;
        }
        if before_ok && after < bytes.len() && bytes[after] == b'=' {
            return Some(pos);
        }
        from = pos + key.len();
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations_are_line_and_column() {
        let src = "<a>\n  <b x=\"1\"\n     y=\"2\"/>\n</a>\n";
        let doc = Doc::parse(src, "t.xml").expect("parses");
        let b = &doc.root.children[0];
        assert_eq!(doc.loc(b.offset).line, 2);
        assert_eq!(doc.loc(b.offset).column, 3);
        let y = doc.attr(b, "y").expect("y");
        assert_eq!(doc.loc(y.offset).line, 3);
        assert_eq!(doc.loc(y.offset).column, 6);
    }

    #[test]
    fn unclosed_element_is_an_error_with_line() {
        let err = Doc::parse("<a>\n<b>\n</a>", "t.xml").expect_err("must fail");
        assert!(matches!(err, XmlError::Syntax { .. }), "{err}");
        assert!(err.line().is_some());
    }

    #[test]
    fn entities_in_text_and_attributes() {
        let doc = Doc::parse("<a v=\"x &amp; y\">1 &lt; 2 &#65;</a>", "t").expect("parses");
        assert_eq!(doc.root.attrs[0].value, "x & y");
        assert_eq!(doc.root.text, "1 < 2 A");
    }
}
