//! A dry run of a PyTorch pickle's opcodes before candle's reader sees it: the reader builds
//! every object in memory, recursively, so a crafted pickle can overflow the stack (a million
//! nested tuples) or the heap (a memo "billion laughs": one small object fetched and nested
//! again and again). This walks the same opcodes (candle's set; anything else is refused),
//! keeping for every stack item only its nesting depth and its size in objects, and refuses
//! the pickle past fixed bounds. Nothing is executed or built.

/// Deepest nesting a state dict needs is a handful; this leaves ample room.
pub const MAX_DEPTH: usize = 256;
/// Objects any one item may hold, counting what memo fetches repeat.
pub const MAX_OBJECTS: u64 = 4_000_000;
/// Memo entries.
pub const MAX_MEMO: usize = 1_000_000;

#[derive(Clone, Copy)]
enum Item {
    Mark,
    Object { depth: usize, size: u64 },
}

/// Walks `pkl` (a `data.pkl`); an error says which bound it crossed or what it could not read.
pub fn check(pkl: &[u8]) -> Result<(), String> {
    let mut stack: Vec<Item> = Vec::new();
    let mut memo: std::collections::HashMap<u32, Item> = std::collections::HashMap::new();
    let mut at = 0usize;
    let take = |at: &mut usize, n: usize| -> Result<&[u8], String> {
        let end = at.checked_add(n).filter(|&e| e <= pkl.len());
        let Some(end) = end else {
            return Err(format!("the pickle ends inside an opcode at byte {at}"));
        };
        let bytes = &pkl[*at..end];
        *at = end;
        Ok(bytes)
    };
    let pop = |stack: &mut Vec<Item>| -> Result<(usize, u64), String> {
        match stack.pop() {
            Some(Item::Object { depth, size }) => Ok((depth, size)),
            Some(Item::Mark) => Err("an opcode takes a mark as its operand".into()),
            None => Err("an opcode pops an empty stack".into()),
        }
    };
    let to_mark = |stack: &mut Vec<Item>| -> Result<(usize, u64), String> {
        let (mut depth, mut size) = (0usize, 0u64);
        loop {
            match stack.pop() {
                Some(Item::Mark) => return Ok((depth, size)),
                Some(Item::Object { depth: d, size: s }) => {
                    depth = depth.max(d);
                    size = size.saturating_add(s);
                }
                None => return Err("no mark to pop to".into()),
            }
        }
    };
    let push = |stack: &mut Vec<Item>, depth: usize, size: u64| -> Result<(), String> {
        if depth > MAX_DEPTH {
            return Err(format!("objects nest deeper than {MAX_DEPTH}"));
        }
        if size > MAX_OBJECTS {
            return Err(format!("an object grows past {MAX_OBJECTS} parts"));
        }
        stack.push(Item::Object { depth, size });
        Ok(())
    };
    // A container on top of the stack takes `(depth, size)` in.
    let extend_top = |stack: &mut Vec<Item>, depth: usize, size: u64| -> Result<(), String> {
        match stack.pop() {
            Some(Item::Object { depth: d, size: s }) => {
                let (d, s) = (d.max(depth + 1), s.saturating_add(size));
                push(stack, d, s)
            }
            _ => Err("no container to add to".into()),
        }
    };
    loop {
        let op = *take(&mut at, 1)?.first().unwrap_or(&0);
        match op {
            0x80 => {
                take(&mut at, 1)?;
            }
            b'c' => {
                for _ in 0..2 {
                    let rest = &pkl[at..];
                    let Some(n) = rest.iter().take(256).position(|&b| b == b'\n') else {
                        return Err("a global name longer than 256 bytes".into());
                    };
                    take(&mut at, n + 1)?;
                }
                push(&mut stack, 1, 1)?;
            }
            b'q' | b'r' => {
                let n = if op == b'q' { 1 } else { 4 };
                let idx = le(take(&mut at, n)?);
                let Some(top) = stack.last().copied() else {
                    return Err("memo put on an empty stack".into());
                };
                if memo.len() >= MAX_MEMO && !memo.contains_key(&idx) {
                    return Err(format!("more than {MAX_MEMO} memo entries"));
                }
                memo.insert(idx, top);
            }
            b'h' | b'j' => {
                let n = if op == b'h' { 1 } else { 4 };
                let idx = le(take(&mut at, n)?);
                match memo.get(&idx) {
                    Some(Item::Object { depth, size }) => push(&mut stack, *depth, *size)?,
                    _ => return Err(format!("memo entry {idx} is fetched before it is put")),
                }
            }
            b')' | b'}' | b'd' | b']' | b'N' | 0x88 | 0x89 => push(&mut stack, 1, 1)?,
            b'(' => stack.push(Item::Mark),
            b'X' => {
                let n = le(take(&mut at, 4)?) as usize;
                take(&mut at, n)?;
                push(&mut stack, 1, 1)?;
            }
            b'J' => {
                take(&mut at, 4)?;
                push(&mut stack, 1, 1)?;
            }
            b'K' => {
                take(&mut at, 1)?;
                push(&mut stack, 1, 1)?;
            }
            b'M' => {
                take(&mut at, 2)?;
                push(&mut stack, 1, 1)?;
            }
            b'G' => {
                take(&mut at, 8)?;
                push(&mut stack, 1, 1)?;
            }
            0x8a => {
                let n = usize::from(take(&mut at, 1)?[0]);
                take(&mut at, n)?;
                push(&mut stack, 1, 1)?;
            }
            b't' => {
                let (d, s) = to_mark(&mut stack)?;
                push(&mut stack, d + 1, s + 1)?;
            }
            0x85..=0x87 => {
                let (mut depth, mut size) = (0, 1u64);
                for _ in 0..(op - 0x84) {
                    let (d, s) = pop(&mut stack)?;
                    depth = depth.max(d);
                    size = size.saturating_add(s);
                }
                push(&mut stack, depth + 1, size)?;
            }
            b'Q' => {
                let (d, s) = pop(&mut stack)?;
                push(&mut stack, d + 1, s + 1)?;
            }
            b'R' | b'b' | 0x81 => {
                let (d1, s1) = pop(&mut stack)?;
                let (d2, s2) = pop(&mut stack)?;
                push(&mut stack, d1.max(d2) + 1, s1.saturating_add(s2) + 1)?;
            }
            b's' => {
                let (d1, s1) = pop(&mut stack)?;
                let (d2, s2) = pop(&mut stack)?;
                extend_top(&mut stack, d1.max(d2), s1.saturating_add(s2))?;
            }
            b'a' => {
                let (d, s) = pop(&mut stack)?;
                extend_top(&mut stack, d, s)?;
            }
            b'u' | b'e' => {
                let (d, s) = to_mark(&mut stack)?;
                extend_top(&mut stack, d, s)?;
            }
            b'.' => return Ok(()),
            other => return Err(format!("opcode 0x{other:02x} at byte {}", at - 1)),
        }
    }
}

fn le(bytes: &[u8]) -> u32 {
    bytes
        .iter()
        .rev()
        .fold(0u32, |n, &b| (n << 8) | u32::from(b))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nesting_and_repetition_past_the_bounds_are_refused() {
        // (((…))) a thousand deep with TUPLE1.
        let mut deep = vec![0x80, 2, b')'];
        deep.extend(std::iter::repeat_n(0x85u8, 1_000));
        deep.push(b'.');
        assert!(check(&deep).unwrap_err().contains("deeper than"));
        // Billion laughs: a list, memoised, then a tuple of it twice, memoised, … 40 times.
        let mut laughs = vec![0x80, 2, b']', b'q', 0];
        for i in 0..40u8 {
            laughs.extend([b'h', i, b'h', i, 0x86, b'q', i + 1]);
        }
        laughs.push(b'.');
        assert!(check(&laughs).unwrap_err().contains("parts"));
        // An unknown opcode, a truncated one, a fetch before a put.
        assert!(
            check(&[0x80, 2, b'i', b'.'])
                .unwrap_err()
                .contains("opcode 0x69")
        );
        assert!(
            check(&[0x80, 2, b'J', 1])
                .unwrap_err()
                .contains("ends inside")
        );
        assert!(
            check(&[0x80, 2, b'h', 3, b'.'])
                .unwrap_err()
                .contains("before it is put")
        );
    }

    #[test]
    fn a_small_state_dict_passes() {
        // {'a': (1, 2.0)}: EMPTY_DICT, BINPUT, BINUNICODE 'a', BININT1 1, BINFLOAT, TUPLE2, SETITEM.
        let mut p = vec![
            0x80, 2, b'}', b'q', 0, b'X', 1, 0, 0, 0, b'a', b'K', 1, b'G',
        ];
        p.extend(2.0f64.to_be_bytes());
        p.extend([0x86, b's', b'.']);
        assert_eq!(check(&p), Ok(()));
    }
}
