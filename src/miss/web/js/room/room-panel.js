// The consultation panel's DOM: who is here, presenter and follow switches, the
// tools, pins, measurements and chat. It only draws and reports clicks; the
// controller (consult.js) decides what they mean.

import { el } from '../format.js';

export const TOOL_HINTS = {
	orbit: 'Drag to turn the model.',
	laser: 'Move over the model: everyone sees where you point.',
	pin: 'Click the model where the pin goes, then write its note.',
	measure: 'Click two points on the model: the distance is shared, in mm.',
};

export function clock( iso ) {
	return new Date( iso ).toLocaleTimeString( [], { hour: '2-digit', minute: '2-digit' } );
}

function dot( colour ) {
	return el( 'span.dot', { style: `background:${colour}` } );
}

export class RoomPanel {
	// handlers: {present(on), follow(on), tool(name), pin(note), cancelPin(), chat(text),
	//            removePin(id), removeMeasurement(id), goto(item), rename(name)}
	constructor( container, handlers, { guest = false, guestName = '' } = {} ) {
		this.handlers = handlers;
		this.root = container;
		container.replaceChildren( ...[
			el( 'div.row', {}, el( 'h2', {}, 'Consultation' ), el( 'span#room-status.muted.small-print', {}, 'connecting…' ) ),
			guest ? this.nameForm( guestName ) : null,
			el( 'ul#participants.participants' ),
			el( 'div.row',
				el( 'button#present', { type: 'button', 'aria-pressed': 'false', onclick: () => handlers.present( this.$( 'present' ).getAttribute( 'aria-pressed' ) !== 'true' ) }, 'Present' ),
				el( 'label.check', {}, el( 'input#follow', { type: 'checkbox', checked: true, onchange: ( e ) => handlers.follow( e.target.checked ) } ), ' Follow the presenter' ) ),
			el( 'div#follow-state.muted', {}, 'Free view: nobody is presenting.' ),
			el( 'div.segmented.tools', { role: 'group', 'aria-label': 'Tool' },
				...[ [ 'orbit', 'Turn' ], [ 'laser', 'Laser' ], [ 'pin', 'Pin' ], [ 'measure', 'Measure' ] ].map( ( [ tool, label ] ) =>
					el( 'button', { type: 'button', dataset: { tool }, 'aria-pressed': String( tool === 'orbit' ), onclick: () => handlers.tool( tool ) }, label ) ) ),
			el( 'span#tool-hint.muted', {}, TOOL_HINTS.orbit ),
			this.pinForm(),
			el( 'h3', {}, 'Pins' ), el( 'ol#pins.pins' ),
			el( 'h3', {}, 'Measurements' ), el( 'ul#measurements.measurements' ),
			el( 'h3', {}, 'Chat' ), el( 'div#chat-log.chat-log', { 'aria-live': 'polite' } ),
			this.chatForm(),
			el( 'div#room-error.notice.error', { role: 'alert', hidden: true } ),
		].filter( Boolean ) );
	}

	$( id ) {
		return this.root.querySelector( `#${id}` );
	}

	nameForm( name ) {
		const submit = ( e ) => {
			e.preventDefault();
			this.handlers.rename( this.$( 'guest-name' ).value.trim() );
		};
		return el( 'form#name-form.row', { onsubmit: submit },
			el( 'label.field.grow', {}, el( 'span', {}, 'Your name in the room' ),
				el( 'input#guest-name', { type: 'text', maxlength: 40, value: name, placeholder: 'e.g. Dr Lee, island clinic' } ) ),
			el( 'button.small', { type: 'submit' }, 'Set' ) );
	}

	pinForm() {
		const submit = ( e ) => {
			e.preventDefault();
			this.handlers.pin( this.$( 'pin-note' ).value );
		};
		return el( 'form#pin-form.row', { hidden: true, onsubmit: submit },
			el( 'input#pin-note', { type: 'text', maxlength: 500, placeholder: 'Note for this pin' } ),
			el( 'button.small.primary', { type: 'submit' }, 'Add pin' ),
			el( 'button.small', { type: 'button', onclick: () => this.handlers.cancelPin() }, 'Cancel' ) );
	}

	chatForm() {
		const submit = ( e ) => {
			e.preventDefault();
			const input = this.$( 'chat-input' );
			if ( input.value.trim() ) this.handlers.chat( input.value );
			input.value = '';
		};
		return el( 'form#chat-form.row', { onsubmit: submit },
			el( 'input#chat-input', { type: 'text', maxlength: 2000, placeholder: 'Message to everyone here', autocomplete: 'off' } ),
			el( 'button.small', { type: 'submit' }, 'Send' ) );
	}

	setStatus( text ) {
		this.$( 'room-status' ).textContent = text;
	}

	showError( text ) {
		this.$( 'room-error' ).textContent = text || '';
		this.$( 'room-error' ).hidden = ! text;
	}

	setTool( tool ) {
		for ( const b of this.root.querySelectorAll( '[data-tool]' ) ) b.setAttribute( 'aria-pressed', String( b.dataset.tool === tool ) );
		this.$( 'tool-hint' ).textContent = TOOL_HINTS[ tool ];
	}

	askPinNote( show ) {
		this.$( 'pin-form' ).hidden = ! show;
		if ( show ) {
			this.$( 'pin-note' ).value = '';
			this.$( 'pin-note' ).focus();
		}
	}

	setParticipants( people, presenter, you ) {
		this.$( 'participants' ).replaceChildren( ...people.map( ( p ) => el( 'li', { dataset: { id: p.id } },
			dot( p.colour ), el( 'span', {}, p.name ),
			p.id === you ? el( 'span.badge.you', {}, 'you' ) : null,
			p.id === presenter ? el( 'span.badge', {}, 'presenting' ) : null ) ) );
		this.$( 'present' ).setAttribute( 'aria-pressed', String( presenter === you ) );
		this.$( 'present' ).textContent = presenter === you ? 'Stop presenting' : 'Present';
	}

	setFollowState( text ) {
		this.$( 'follow-state' ).textContent = text;
	}

	// mine(item): may this participant remove it (its author, or the owner)?
	setPins( pins, mine ) {
		this.$( 'pins' ).replaceChildren( ...pins.map( ( pin ) => el( 'li', { dataset: { id: pin.id } },
			dot( pin.colour ),
			el( 'button.link', { type: 'button', title: 'Turn the view to this pin', onclick: () => this.handlers.goto( pin ) }, pin.note || '(no note)' ),
			el( 'span.muted.small-print', {}, ` ${pin.author}, ${clock( pin.at )}` ),
			mine( pin ) ? el( 'button.small.danger', { type: 'button', title: 'Remove the pin', onclick: () => this.handlers.removePin( pin.id ) }, '×' ) : null ) ) );
	}

	setMeasurements( items, mine ) {
		this.$( 'measurements' ).replaceChildren( ...items.map( ( m ) => el( 'li', { dataset: { id: m.id } },
			dot( m.colour ), el( 'strong.mono', {}, `${m.mm.toFixed( 1 )} mm` ),
			el( 'span.muted.small-print', {}, ` ${m.author}, ${clock( m.at )}` ),
			mine( m ) ? el( 'button.small.danger', { type: 'button', title: 'Remove', onclick: () => this.handlers.removeMeasurement( m.id ) }, '×' ) : null ) ) );
	}

	setChat( messages ) {
		const log = this.$( 'chat-log' );
		log.replaceChildren( ...messages.map( ( m ) => el( 'div.chat-line', { dataset: { id: m.id } },
			// the author's colour as a dot: half the room's colours are too light for text
			el( 'span.mono.muted', {}, clock( m.at ) + ' ' ), dot( m.colour ), el( 'strong', {}, m.author ), ': ', m.text ) ) );
		log.scrollTop = log.scrollHeight;
	}
}
