#!/usr/bin/env python3
"""Merge Twinswarm's messages (conf/messages/twinswarm_messages.xml) into a pprzlink v1.0
messages.xml, as text: the base file stays byte for byte what it was except for the added
messages (inserted at the end of their class, after a marker comment) and the moved ids.

    python3 paparazzi/merge_messages.py BASE_messages.xml ADDITIONS.xml OUT_messages.xml

BASE is the pristine pprzlink file of the tree (sw/ext/pprzlink/message_definitions/v1.0/
messages.xml), never an already merged one, so the output is the same every time (build_nps.sh
compares it with var/messages.xml to decide whether to regenerate the C headers).
Fails (exit 1) if a name or id would be duplicated in a class. Stdlib only.
"""
import re
import sys
import xml.etree.ElementTree as ET

MARK = "<!-- added by Twinswarm (paparazzi/conf/messages/twinswarm_messages.xml) -->"


def class_span(text, name):
    m = re.search(r'<msg_class\s+name="%s"[^>]*>' % re.escape(name), text)
    if not m:
        sys.exit(f"merge_messages: no msg_class {name}")
    end = text.find("</msg_class>", m.end())
    return m.end(), end


def main():
    base_path, add_path, out_path = sys.argv[1:4]
    text = open(base_path, encoding="utf-8").read()
    add_text = open(add_path, encoding="utf-8").read()
    add = ET.fromstring(add_text)
    for cls in add.findall("msg_class"):
        cname = cls.get("name")
        for mv in cls.findall("move"):
            start, end = class_span(text, cname)
            body = text[start:end]
            pat = re.compile(r'(<message\s+name="%s"\s+id=")%s(")' % (re.escape(mv.get("name")), re.escape(mv.get("from"))))
            body, n = pat.subn(lambda m: m.group(1) + mv.get("to") + m.group(2), body)
            if n != 1:
                sys.exit(f"merge_messages: {cname}/{mv.get('name')} id {mv.get('from')} found {n} times")
            text = text[:start] + body + text[end:]
        blocks = []
        for msg in cls.findall("message"):
            name = msg.get("name")
            m = re.search(r'( *)<message\s+name="%s".*?</message>' % re.escape(name), add_text, re.S)
            block = m.group(0)
            # Paparazzi's OCaml XML parser (xml-light: gen_aircraft, link, server) rejects a raw
            # '>' or '<' in text, e.g. in a description
            text_only = re.sub(r"<[^<>]*>", "", block)
            if "<" in text_only or ">" in text_only:
                sys.exit(f"merge_messages: {cname}/{name}: raw < or > in text (xml-light fails)")
            blocks.append(block)
        if blocks:
            start, end = class_span(text, cname)
            ins = "\n    " + MARK + "\n" + "\n\n".join(blocks) + "\n\n  "
            # insert before the class's closing tag, after its last message
            head = text[:end].rstrip()
            text = head + "\n" + ins + text[end:]
    # check: unique names and ids per class
    root = ET.fromstring(text.encode("utf-8"))
    for c in root.findall("msg_class"):
        names, ids = set(), set()
        for m in c.findall("message"):
            i = int(m.get("id"), 0)
            if m.get("name") in names or i in ids:
                sys.exit(f"merge_messages: duplicate {c.get('name')}/{m.get('name')} id {i}")
            names.add(m.get("name"))
            ids.add(i)
    with open(out_path, "w", encoding="utf-8") as f:
        f.write(text)


if __name__ == "__main__":
    main()
