//! Errors with stable codes and byte offsets.
//!
//! Every rule of spec/VDAG.md § Validation rules has one [`ErrorCode`]; the
//! code strings (`E001` …) are stable across versions and are what the
//! conformance suite's malformed-file cases expect.

use std::fmt;

macro_rules! error_codes {
    ($( $(#[$doc:meta])* $variant:ident = $code:literal, $name:literal; )*) => {
        /// The stable identifier of a validation rule (spec/VDAG.md § Validation rules).
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
        pub enum ErrorCode {
            $( $(#[$doc])* $variant, )*
        }

        impl ErrorCode {
            /// Every code, in numeric order.
            pub const ALL: &'static [ErrorCode] = &[$(ErrorCode::$variant,)*];

            /// The stable code, such as `"E002"`.
            pub fn code(self) -> &'static str {
                match self { $(ErrorCode::$variant => $code,)* }
            }

            /// The stable short name, such as `"bad-magic"`.
            pub fn name(self) -> &'static str {
                match self { $(ErrorCode::$variant => $name,)* }
            }

            /// Looks a code up by its code string or its name.
            pub fn parse(s: &str) -> Option<ErrorCode> {
                match s {
                    $($code | $name => Some(ErrorCode::$variant),)*
                    _ => None,
                }
            }
        }
    };
}

error_codes! {
    /// The file is shorter than the 128-byte header.
    TruncatedHeader = "E001", "truncated-header";
    /// The first eight bytes are not the `.vdag` magic.
    BadMagic = "E002", "bad-magic";
    /// The major version is not 1 or 2 (or, for a 1.0-only reader, not 1).
    UnsupportedVersion = "E003", "unsupported-version";
    /// A required feature bit this reader does not know is set.
    UnknownRequiredFeature = "E004", "unknown-required-feature";
    /// The header size field is not 128.
    BadHeaderSize = "E005", "bad-header-size";
    /// The depth is outside 2 ..= 21.
    DepthOutOfRange = "E006", "depth-out-of-range";
    /// The attribute kind is not in the registry.
    UnknownAttributeKind = "E007", "unknown-attribute-kind";
    /// The root cube's corner is not finite or its size is not finite and positive.
    BadRootCube = "E008", "bad-root-cube";
    /// A reserved header or section-table field is not zero.
    NonzeroReserved = "E009", "nonzero-reserved";
    /// The file's length differs from the header's file size (truncated or extended).
    FileSizeMismatch = "E010", "file-size-mismatch";
    /// The header checksum does not match.
    HeaderChecksum = "E011", "header-checksum";
    /// The section table runs past the end of the file or has too many or too few entries.
    BadSectionTable = "E012", "bad-section-table";
    /// The file exceeds the reader's size limit.
    FileTooLarge = "E013", "file-too-large";
    /// A section's byte range runs past the end of the file.
    SectionOutOfBounds = "E020", "section-out-of-bounds";
    /// A section does not start at a multiple of 8.
    SectionMisaligned = "E021", "section-misaligned";
    /// Sections overlap or are not stored in table order.
    SectionOverlap = "E022", "section-overlap";
    /// Bytes between sections (or after the section table) are not minimal zero padding.
    BadPadding = "E023", "bad-padding";
    /// The level sections are missing, duplicated, out of order or of the wrong kind.
    BadLevelSections = "E024", "bad-level-sections";
    /// A section kind this reader does not know is not marked optional.
    UnknownSectionKind = "E025", "unknown-section-kind";
    /// A pointer width is not 1 to 4 (node level) or not 0 (other sections).
    BadPointerWidth = "E026", "bad-pointer-width";
    /// A pointer width is not the smallest that addresses the child level.
    PointerWidthNotMinimal = "E027", "pointer-width-not-minimal";
    /// A section's checksum does not match.
    SectionChecksum = "E028", "section-checksum";
    /// A level exceeds the per-level limits (bytes or leaves).
    LevelTooLarge = "E030", "level-too-large";
    /// The root level holds other than one node (or zero, with every level empty).
    BadRootLevel = "E040", "bad-root-level";
    /// A node has an empty child mask.
    EmptyChildMask = "E041", "empty-child-mask";
    /// A node record runs past the end of its section.
    TruncatedNode = "E042", "truncated-node";
    /// A section's item count differs from what its bytes hold.
    ItemCountMismatch = "E043", "item-count-mismatch";
    /// The padding after a node's pointers is not zero.
    NonzeroNodePadding = "E044", "nonzero-node-padding";
    /// A pointer lies outside the child level.
    PointerOutOfRange = "E045", "pointer-out-of-range";
    /// A pointer does not address the start of a node record.
    PointerNotAtNode = "E046", "pointer-not-at-node";
    /// A node or leaf of a level below the root is referenced by no pointer.
    UnreferencedNode = "E047", "unreferenced-node";
    /// A leaf mask is zero.
    EmptyLeafMask = "E048", "empty-leaf-mask";
    /// Attribute kind 0 but a node's attribute bits are not zero.
    NonzeroAttribute = "E060", "nonzero-attribute";
    /// Attribute kind 1 but a node's stored voxel count is wrong.
    WrongVoxelCount = "E061", "wrong-voxel-count";
    /// The header's voxel count differs from the voxels in the DAG.
    HeaderVoxelCount = "E062", "header-voxel-count";
    /// A voxel colour section is present without attribute kind 1, twice, or with a wrong count.
    BadColorSection = "E063", "bad-color-section";
    /// 2.0: a node level's reference widths are not 1 ≤ w1 ≤ w2 ≤ w3 ≤ 40, or bytes 5..8 of another section's entry are not zero.
    BadWidths = "E070", "bad-widths";
    /// 2.0: a node record runs past the end of its level.
    TruncatedRecord2 = "E071", "truncated-record-2";
    /// 2.0: the bits after a record's last reference are not zero.
    NonzeroBitPadding = "E072", "nonzero-bit-padding";
    /// 2.0: a reference's target is not a record start (or leaf), or a sequential run leaves its level.
    ReferenceOutOfRange2 = "E073", "reference-out-of-range-2";
    /// 2.0: a reference does not use the smallest width holding it, or the widths are not the level's minimising triple.
    WidthNotMinimal = "E074", "width-not-minimal";
    /// 2.0: two nodes (leaves) of a level are equal or mirror images of each other.
    DuplicateClass = "E075", "duplicate-class";
    /// 2.0: a shared node is not stored as its canonical member, or a reference does not carry the least reflection.
    NotCanonical = "E076", "not-canonical";
    /// 2.0: a level's nodes are not in the order of §23.7.
    BadLevelOrder = "E077", "bad-level-order";
    /// 2.0: a node is named once but shared, sequential but named other than once by one run, or not named.
    BadSharing = "E078", "bad-sharing";
    /// 2.0: a node level's item count differs from the records it holds.
    ItemCountMismatch2 = "E079", "item-count-mismatch-2";
    /// A packed colour section is present without attribute kind 1, beside another colour section, with a wrong count, or shorter than its directory and trailer.
    BadPackedColorSection = "E080", "bad-packed-color-section";
    /// A packed colour section's trailer has a block shift other than 6, 7 or 8, unknown flags, an error bound over 127, a measured error over the bound, a non-zero reserved byte or an impossible squared error.
    BadColorTrailer = "E081", "bad-color-trailer";
    /// A packed colour directory entry places a block outside the blocks, out of order, or not right after the block before; or its unused bits are not zero.
    BadColorDirectory = "E082", "bad-color-directory";
    /// A packed colour block header is invalid (width over 8, alpha width without alpha, a palette larger than the block, a direct block with a palette size, a uniform mask past the block).
    BadColorBlock = "E083", "bad-color-block";
    /// A packed colour block's length by its header differs from its length by the directory.
    ColorBlockLength = "E084", "color-block-length";
    /// The padding bits after a packed colour block's bit stream are not zero.
    ColorBlockPadding = "E085", "color-block-padding";
    /// A palette index of a packed colour block is not below its palette size.
    ColorIndexOutOfRange = "E086", "color-index-out-of-range";
    /// A packed colour entry starts its interval past 255.
    ColorValueOutOfRange = "E087", "color-value-out-of-range";
    /// A packed colour block's split mask names sub-blocks past the block or ones that are uniform too, or a split sub-block's position is not inside it (format 1.2).
    BadSplitSubBlock = "E088", "bad-split-sub-block";
}

impl fmt::Display for ErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}", self.code(), self.name())
    }
}

/// A violation of the format: what rule, where, and a human message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FormatError {
    /// The rule broken.
    pub code: ErrorCode,
    /// Byte offset in the file of the offending bytes.
    pub offset: u64,
    /// The level concerned, if any.
    pub level: Option<u8>,
    /// The node concerned, as its index in its level (in storage order), if any.
    pub node: Option<u64>,
    /// What is wrong, for people.
    pub message: String,
}

impl FormatError {
    /// A violation at `offset` with no level or node.
    pub fn new(code: ErrorCode, offset: u64, message: impl Into<String>) -> Self {
        FormatError {
            code,
            offset,
            level: None,
            node: None,
            message: message.into(),
        }
    }

    /// Attaches the level concerned.
    pub fn at_level(mut self, level: u8) -> Self {
        self.level = Some(level);
        self
    }

    /// Attaches the node concerned (its index within its level).
    pub fn at_node(mut self, node: u64) -> Self {
        self.node = Some(node);
        self
    }
}

impl fmt::Display for FormatError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} at byte {:#x}", self.code, self.offset)?;
        if let Some(level) = self.level {
            write!(f, " (level {level}")?;
            if let Some(node) = self.node {
                write!(f, ", node {node}")?;
            }
            write!(f, ")")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for FormatError {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_unique_and_parse_back() {
        let mut codes: Vec<_> = ErrorCode::ALL.iter().map(|c| c.code()).collect();
        codes.sort();
        codes.dedup();
        assert_eq!(codes.len(), ErrorCode::ALL.len());
        for &c in ErrorCode::ALL {
            assert_eq!(ErrorCode::parse(c.code()), Some(c));
            assert_eq!(ErrorCode::parse(c.name()), Some(c));
        }
    }

    #[test]
    fn display_names_offset_level_node() {
        let e = FormatError::new(ErrorCode::EmptyChildMask, 0x1c8, "node has no children")
            .at_level(3)
            .at_node(7);
        assert_eq!(
            e.to_string(),
            "E041 empty-child-mask at byte 0x1c8 (level 3, node 7): node has no children"
        );
    }
}
