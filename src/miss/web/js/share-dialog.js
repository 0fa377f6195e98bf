// The owner's share dialog on the viewer: make a link (expiry, download and
// annotate permissions, a label), copy its URL -- shown this once, since the
// server keeps only a hash of the token -- and list or revoke the links made.

import { api } from './api.js';
import { el } from './format.js';
import { viewParams } from './viewer/deep-link.js';

const EXPIRIES = [ [ 3600, '1 hour' ], [ 86400, '1 day' ], [ 7 * 86400, '7 days' ], [ 30 * 86400, '30 days' ] ];

function when( iso ) {
	return new Date( iso ).toLocaleString( [], { dateStyle: 'medium', timeStyle: 'short' } );
}

export class ShareDialog {
	constructor( modelId, { burnedIn = false } = {} ) {
		this.modelId = modelId;
		this.dialog = el( 'dialog#share-dialog.share-dialog', {},
			el( 'form', { method: 'dialog', onsubmit: ( e ) => this.create( e ) },
				el( 'h2', {}, 'Share this model' ),
				burnedIn ? el( 'div.notice.error', {}, 'The scanner flagged text burned into these images; it may show patient identity in the pixels. Check before sharing.' ) : null,
				el( 'label.field', {}, el( 'span', {}, 'Label (who it is for; only you see it)' ), el( 'input#share-label', { type: 'text', maxlength: 200, placeholder: 'e.g. Dr Lee, island clinic' } ) ),
				el( 'label.field', {}, el( 'span', {}, 'Message for the people you share with (optional)' ), el( 'input#share-message', { type: 'text', maxlength: 1000, placeholder: 'e.g. Please look at the left temporal bone' } ) ),
				el( 'label.field', {}, el( 'span', {}, 'Expires after' ),
					el( 'select#share-expiry', {}, ...EXPIRIES.map( ( [ s, label ] ) => el( 'option', { value: s, selected: s === 86400 }, label ) ) ) ),
				el( 'label.check', {}, el( 'input#share-annotate', { type: 'checkbox', checked: true } ), ' may join the consultation (pins, chat, measure)' ),
				el( 'label.check', {}, el( 'input#share-download', { type: 'checkbox' } ), ' may download the model files' ),
				el( 'label.check', {}, el( 'input#share-volume', { type: 'checkbox' } ), ' may see the scan itself in 3-D (its de-identified voxels)' ),
				el( 'label.check', {}, el( 'input#share-here', { type: 'checkbox', checked: true } ), ' opens on the view I see now (camera; the scan and slices if allowed)' ),
				burnedIn ? el( 'label.check', {}, el( 'input#share-burned-ok', { type: 'checkbox' } ), ' I have looked at the slices: no identity shows in the pixels' ) : null,
				el( 'div.row', {},
					el( 'button#share-create.primary', { type: 'submit' }, 'Create link' ),
					el( 'button', { type: 'button', onclick: () => this.dialog.close() }, 'Close' ) ),
				el( 'div#share-result.share-result', { hidden: true },
					el( 'span.muted', {}, 'Copy the link now: it is shown only once.' ),
					el( 'div.row', {}, el( 'input#share-url', { type: 'text', readonly: true } ),
						el( 'button#share-copy.small', { type: 'button', onclick: () => this.copy() }, 'Copy' ) ) ),
				el( 'div#share-error.notice.error', { role: 'alert', hidden: true } ),
				el( 'h3', {}, 'Links to this model' ),
				el( 'ul#share-list.share-list' ) ) );
		document.body.append( this.dialog );
	}

	$( id ) {
		return this.dialog.querySelector( `#${id}` );
	}

	async open() {
		this.$( 'share-result' ).hidden = true;
		this.dialog.showModal();
		await this.refresh();
	}

	async create( event ) {
		event.preventDefault();
		this.$( 'share-error' ).hidden = true;
		try {
			const link = await api.createShare( {
				model: this.modelId,
				expires_in: Number( this.$( 'share-expiry' ).value ),
				can_annotate: this.$( 'share-annotate' ).checked,
				can_download: this.$( 'share-download' ).checked,
				can_view_volume: this.$( 'share-volume' ).checked,
				burned_in_confirmed: Boolean( this.$( 'share-burned-ok' )?.checked ),
				label: this.$( 'share-label' ).value,
				message: this.$( 'share-message' ).value,
			} );
			this.shown = link.id; // the link whose URL the copy field holds
			const url = new URL( link.url, location.origin );
			if ( this.$( 'share-here' ).checked ) {
				for ( const [ name, value ] of viewParams( link.can_view_volume ) ) url.searchParams.set( name, value );
			}
			this.$( 'share-url' ).value = url.href;
			this.$( 'share-result' ).hidden = false;
			this.$( 'share-url' ).select();
			await this.refresh();
		} catch ( err ) {
			this.showError( err );
		}
	}

	async copy() {
		const input = this.$( 'share-url' );
		input.select();
		try {
			await navigator.clipboard.writeText( input.value );
			this.$( 'share-copy' ).textContent = 'Copied';
		} catch ( err ) {
			document.execCommand?.( 'copy' ); // http:// pages on another host have no clipboard API
		}
	}

	showError( err ) {
		this.$( 'share-error' ).textContent = err.message || String( err );
		this.$( 'share-error' ).hidden = false;
	}

	async refresh() {
		try {
			const all = await api.shares( this.modelId );
			// Links that open nothing any more are kept for the audit, not listed here.
			const links = all.filter( ( link ) => link.status === 'active' );
			this.$( 'share-list' ).replaceChildren( ...links.map( ( link ) => this.item( link ) ) );
			if ( ! links.length ) this.$( 'share-list' ).append( el( 'li.muted', {}, 'no active link' ) );
			const gone = all.length - links.length;
			if ( gone ) this.$( 'share-list' ).append( el( 'li.muted.small-print', {}, `${gone} expired or revoked ${gone === 1 ? 'link' : 'links'} not shown` ) );
		} catch ( err ) {
			this.showError( err );
		}
	}

	item( link ) {
		const rights = [ link.can_annotate ? 'consult' : 'view', link.can_view_volume ? 'scan' : null, link.can_download ? 'download' : null ].filter( Boolean ).join( ' + ' );
		const revoke = async () => {
			if ( ! confirm( `Revoke the link “${link.label || 'no label'}”? Whoever has it loses access at once.` ) ) return;
			try {
				await api.revokeShare( link.id );
				if ( this.shown === link.id ) { // its URL is no use to anyone now
					this.$( 'share-url' ).value = '';
					this.$( 'share-result' ).hidden = true;
				}
				await this.refresh();
			} catch ( err ) {
				this.showError( err );
			}
		};
		return el( 'li', { dataset: { id: link.id, status: link.status } },
			el( 'strong', {}, link.label || '(no label)' ),
			el( 'span.muted.small-print', {}, ` ${rights} · ${link.status === 'active' ? 'until ' + when( link.expires ) : link.status}` ),
			link.status === 'active' ? el( 'button.small.danger', { type: 'button', onclick: revoke }, 'Revoke' ) : null );
	}
}
