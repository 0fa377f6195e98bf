// The volume page's privacy card: what de-identification removed (attribute
// names only), the burned-in annotation warning, and for the owner the original
// identity, fetched only when asked for (and logged in the audit).

import { api } from './api.js';
import { el, fill } from './format.js';

export function showPrivacy( card, volume ) {
	const d = volume.deidentification || {};
	const removed = d.removed || [];
	const facts = removed.length || d.uids_remapped
		? `Removed ${removed.length} identifying attribute(s); ${d.uids_remapped || 0} UID(s) remapped; ${d.private_tags_dropped || 0} private tag(s) dropped.`
		: 'No patient identity came with this scan.';
	const reveal = async () => {
		try {
			const identity = await api.identity( volume.id );
			card.querySelector( '#identity' ).replaceChildren( ...Object.entries( identity.patient ).map( ( [ k, v ] ) =>
				el( 'tr', {}, el( 'th', {}, k ), el( 'td', {}, v ) ) ) );
		} catch ( err ) {
			card.querySelector( '#identity' ).replaceChildren( el( 'tr', {}, el( 'td.muted', {}, err.message ) ) );
		}
	};
	fill( card,
		el( 'h2', {}, 'Patient identity' ),
		el( 'span.muted', { title: d.profile || '' }, facts ),
		volume.burned_in_annotation ? el( 'div.notice.error', {}, 'The scanner flagged text burned into the images (BurnedInAnnotation = YES): the pixels may show identity. Check before sharing.' ) : null,
		removed.length ? el( 'button.small', { type: 'button', id: 'show-identity', onclick: reveal, title: 'Only you, the owner, can see this; it is never shared' }, 'Show original identity' ) : null,
		el( 'table#identity.stats' ) );
}
